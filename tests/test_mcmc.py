"""--strategy mcmc: the relocation keeps what a surfel looks like, dead surfels move onto live ones, the count grows
to the budget and stays, and an interrupted run resumes to the same parameters."""
import json
import math

import pytest
import torch

import splatzoo
from splatzoo.data import load_scene
from splatzoo.errors import SplatzooError
from splatzoo.runs import train
from splatzoo.training import TrainConfig
from splatzoo.training.mcmc import DEAD_OPACITY, add_surfels, inject_noise, relocate_dead, relocated


@pytest.mark.parametrize("opacity", [0.05, 0.3, 0.9])
@pytest.mark.parametrize("copies", [1, 2, 5])
def test_relocated_stack_has_the_sources_peak_and_integral(opacity, copies):
    o, s = torch.tensor([opacity], dtype=torch.float64), torch.tensor([[0.7, 0.7]], dtype=torch.float64)
    new_o, new_s = relocated(o, s, torch.tensor([copies]))
    if copies == 1:
        assert torch.allclose(new_o, o) and torch.allclose(new_s, s)
    x = torch.linspace(-6, 6, 801, dtype=torch.float64)
    r2 = x[:, None] ** 2 + x[None] ** 2
    dx = float(x[1] - x[0])
    stack = 1 - (1 - new_o * torch.exp(-r2 / (2 * new_s[0, 0] ** 2))) ** copies
    single = o * torch.exp(-r2 / (2 * s[0, 0] ** 2))
    assert float(stack.max()) == pytest.approx(opacity, rel=1e-9)  # the peak
    assert float(stack.sum() * dx * dx) == pytest.approx(float(single.sum() * dx * dx), rel=1e-6)  # the integral
    assert float(single.sum() * dx * dx) == pytest.approx(opacity * 2 * math.pi * 0.49, rel=1e-6)
    if copies > 1:
        assert new_o < o and new_s[0, 0] < s[0, 0]


def model_with_dead(n=60, dead=10):
    g = torch.Generator().manual_seed(0)
    pts, cols = torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g)
    m = splatzoo.create_model("gabor", pts, cols, n_waves=2)
    with torch.no_grad():
        m.logit_opacity.uniform_(-1, 2, generator=g)
        m.logit_opacity[:dead] = -8.0  # opacity 3e-4: dead
    return m


def test_dead_surfels_move_onto_live_ones():
    m = model_with_dead()
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=1e-3)
    m.means.sum().backward()
    opt.step()
    before = {k: v.detach().clone() for k, v in m.per_primitive().items()}
    assert relocate_dead(m, opt, torch.Generator().manual_seed(1)) == 10
    opacity = torch.sigmoid(m.logit_opacity)
    assert m.num_primitives == 60 and bool((opacity > DEAD_OPACITY).all())
    for i in range(10):  # each moved surfel is a copy of a live source: same position, colour, waves
        src = int(((before["means"] - m.means[i]).norm(dim=1) == 0).nonzero()[-1])
        assert src >= 10
        for name in ("color_base", "color_diff", "wave_weights", "wave_freqs", "quats"):
            assert torch.equal(getattr(m, name)[i], before[name][src]), name
        assert opt.state[m.means]["exp_avg"][i].eq(0).all()
    assert relocate_dead(m, opt, torch.Generator().manual_seed(1)) == 0  # nothing left to move


def test_a_textured_surfel_with_transparent_texels_is_dead_and_relocated():
    """Dead or alive goes by the effective opacity: opacity x the most opaque texel's alpha. The relocation rescales
    the scalar opacity and copies the source's texture."""
    g = torch.Generator().manual_seed(0)
    m = splatzoo.create_model("textured", torch.randn(40, 3, generator=g), torch.rand(40, 3, generator=g))
    with torch.no_grad():
        m.logit_opacity.fill_(2.0)  # opacity 0.88 everywhere
        m.texture_alpha_logit.uniform_(-1, 3, generator=g)
        m.texture_alpha_logit[:4] = -12.0  # alpha 6e-6 at every texel: draws nothing
    effective = m.effective_opacity()
    assert torch.allclose(effective, torch.sigmoid(m.logit_opacity)
                          * torch.sigmoid(m.texture_alpha_logit).amax(dim=(1, 2, 3)))
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=1e-3)
    before = {k: v.detach().clone() for k, v in m.per_primitive().items()}
    assert relocate_dead(m, opt, torch.Generator().manual_seed(1)) == 4
    assert bool((m.effective_opacity() > DEAD_OPACITY).all())
    for i in range(4):  # a copy of a live source: its texture as it was, its opacity the relocation's (lower)
        src = int(((before["means"] - m.means[i]).norm(dim=1) == 0).nonzero()[-1])
        assert src >= 4
        assert torch.equal(m.texture_alpha_logit[i], before["texture_alpha_logit"][src])
        assert torch.equal(m.texture_rgb[i], before["texture_rgb"][src])
        assert m.logit_opacity[i] == m.logit_opacity[src] < before["logit_opacity"][src]
    assert relocate_dead(m, opt, torch.Generator().manual_seed(1)) == 0


def test_added_surfels_share_their_sources_coverage():
    m = model_with_dead(dead=0)
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=1e-3)
    coverage = (torch.sigmoid(m.logit_opacity) * torch.exp(m.log_scales).prod(1)).sum()
    assert add_surfels(m, opt, 15, torch.Generator().manual_seed(2)) == 15
    assert m.num_primitives == 75
    assert all(p.shape[0] == 75 for g in opt.param_groups for p in g["params"])
    # each stack keeps its source's alpha integral; the sum of o s^2 over its copies is close to it (not equal:
    # the stack's alpha is not the sum of its copies')
    after = (torch.sigmoid(m.logit_opacity) * torch.exp(m.log_scales).prod(1)).sum()
    assert 0.9 * coverage < after < 1.3 * coverage


def test_noise_moves_only_nearly_dead_surfels_along_their_plane():
    m = model_with_dead()
    before = m.means.detach().clone()
    inject_noise(m, 1e-3, torch.Generator().manual_seed(3))
    moved = (m.means.detach() - before).norm(dim=1)
    assert moved[:10].min() > 0 and moved[10:].max() < 1e-3 * moved[:10].min()
    from splatzoo.geometry import quat_to_rotmat

    normal = quat_to_rotmat(m.quats.detach())[:, :, 2]
    along_normal = ((m.means.detach() - before)[:10] * normal[:10]).sum(1).abs()
    assert (along_normal < 1e-5 * moved[:10]).all()


def test_mcmc_training_grows_to_the_budget_and_resumes_exactly(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene

    scene = load_scene(make_synthetic_scene("sweater", tmp_path / "sweater", views=8, width=40, height=40))
    cfg = TrainConfig(iterations=40, num_primitives=100, max_primitives=130, strategy="mcmc", densify_from=0,
                      densify_interval=5, log_every=5, backend="cpu", checkpoint_minutes=0)
    full = train(scene, "gabor", {}, cfg, tmp_path / "full", progress=False, evaluate_at_end=False)
    counts = [json.loads(x)["num_primitives"] for x in (tmp_path / "full" / "train_log.jsonl").read_text().splitlines()
              if "num_primitives" in x]
    assert counts[0] > 100 and max(counts) == counts[-1] == 130
    part = train(scene, "gabor", {}, cfg, tmp_path / "part", progress=False, evaluate_at_end=False, stop_after=23)
    resumed = train(scene, "gabor", {}, None, tmp_path / "part", resume=True, progress=False, evaluate_at_end=False)
    a, b = full.model.state_dict(), resumed.model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    del part
    with pytest.raises(SplatzooError, match="strategy"):
        TrainConfig(strategy="gsplat").validate()
