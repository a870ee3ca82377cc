"""Adaptive waves: the Surfels.wave_counts contract, wave pruning in the gabor model, its packed checkpoint,
densification with pruned waves, the trainer hook, and view-dependent (SH) colour for the gabor family."""
import json
import math

import pytest
import torch

import splatzoo
from scenes import random_scene
from splatzoo import Camera, Surfels, rasterize
from splatzoo.errors import ShapeError
from splatzoo.rasterizers.reference import rasterize_reference
from splatzoo.training.densify import DensifyStats, densify_and_prune

CAM = Camera.look_at([0.0, 0.0, -3.5], [0.0, 0.0, 0.0], width=32, height=32, fov_deg=45.0)
BACKENDS = ["reference", "cpu"]
COLOR_PARAMS = ["residual", "paper", "per-wave"]
# per parametrisation: the base colour, the colour the waves scale (per-wave: none, each wave has its own), buffers
# that only waved surfels store
COLOR_NAMES = {"residual": ("color_base", "color_diff", ()), "paper": ("color_a", "color_b", ("folded_weights",)),
               "per-wave": ("color_base", None, ())}


def point_cloud(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    return d / d.norm(dim=1, keepdim=True), torch.rand(n, 3, generator=g)


def adaptive_model(threshold=0.01, **kw):
    pts, cols = point_cloud()
    m = splatzoo.create_model("gabor", pts, cols, seed=1, prune_waves=threshold, **kw)
    with torch.no_grad():
        m.logit_opacity.fill_(1.0)
        g = torch.Generator().manual_seed(3)  # give the waves real amplitude
        if m.per_wave:  # amplitudes as residual's w d would have them
            m.wave_weights.mul_(torch.empty(m.wave_weights.shape).uniform_(-1, 1, generator=g))
        elif m.residual:
            m.color_diff.uniform_(-0.5, 0.5, generator=g)
        else:
            m.color_b.uniform_(0, 1, generator=g)
    return m


def render(m, backend="reference"):
    with torch.no_grad():
        return rasterize(m.surfels(CAM), CAM, backend=backend)


# ---- the contract -----------------------------------------------------------------------------------------------

def test_positional_surfels_still_work_and_counts_are_validated():
    s, cam = random_scene(20, 3, seed=1)
    assert s.wave_counts is None and Surfels(*s.tensors().values()).wave_counts is None
    s.wave_counts = torch.tensor([0, 3] * 10)
    assert s.index(torch.arange(5)).wave_counts.tolist() == [0, 3, 0, 3, 0]
    assert s.to(dtype=torch.float64).wave_counts.dtype == torch.int64  # counts stay integers
    s.validate()
    for bad, msg in ((torch.full((20,), 4), r"\[0, K=3\]"), (torch.zeros(19, dtype=torch.int32), "shape"),
                     (torch.zeros(20), "integer")):
        s.wave_counts = bad
        with pytest.raises(ShapeError, match=msg):
            s.validate()


def test_reference_counts_mask_values_and_gradients():
    s, cam = random_scene(40, 3, seed=2, dtype=torch.float64)
    s.wave_counts = torch.randint(0, 4, (40,), generator=torch.Generator().manual_seed(0))
    leaves = s.map(lambda t: t.detach().clone().requires_grad_(True))
    out = rasterize_reference(leaves, cam)
    out.rgb.sum().backward()
    unused = torch.arange(3)[None] >= s.wave_counts[:, None]
    assert leaves.wave_amplitudes.grad[unused].abs().max() == 0 and leaves.wave_phases.grad[unused].abs().max() == 0
    # the same as deleting the unused waves: zero their amplitude
    amps = torch.where(unused[..., None], torch.zeros_like(s.wave_amplitudes), s.wave_amplitudes)
    plain = Surfels(s.means, s.quats, s.scales, s.opacities, s.base_color, s.wave_vectors, s.wave_phases, amps)
    torch.testing.assert_close(out.rgb.detach(), rasterize_reference(plain, cam).rgb, atol=1e-12, rtol=0)


# ---- pruning ----------------------------------------------------------------------------------------------------

def test_pruning_keeps_fewer_waves_and_only_removes_small_ones():
    m = adaptive_model(threshold=1e-9)  # removes only waves that are exactly zero
    with torch.no_grad():
        m.wave_weights[:32, 1:] = 0.0
        m.wave_weights[32:48] = 0.0
    before = render(m)
    info = m.prune_waves(1e-9)
    assert info["removed"] == 32 * 3 + 16 * 4 and m.summary()["waves_active"] == 256 - info["removed"]
    assert m.wave_counts[:32].eq(1).all() and m.wave_counts[32:48].eq(0).all() and m.wave_counts[48:].eq(4).all()
    after = render(m)
    torch.testing.assert_close(after.rgb, before.rgb, atol=1e-6, rtol=0)  # zero waves: nothing visible changes
    # a real threshold removes exactly the waves whose contribution is below it
    m2 = adaptive_model(threshold=0.02)
    expected = int((m2.wave_statistics()[1] < 0.02).sum())
    assert m2.prune_waves(0.02)["removed"] == expected > 0
    assert m2.summary()["waves_active"] == 256 - expected


def test_wave_statistics_match_sampling_over_the_gaussian():
    """mean and opacity x std of each wave over u,v ~ N(0, I), against a Monte-Carlo estimate."""
    m = adaptive_model()
    with torch.no_grad():
        m.wave_freqs[:4] = torch.tensor([0.0, 0.05, 0.2, 1.5])[:, None]  # from constant to many cycles per sigma
        m.logit_opacity[:4] = torch.tensor([0.0, 1.0, -1.0, 2.0])
    mean, contribution = m.wave_statistics()
    uv = torch.randn(400_000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    s = m.surfels(CAM)
    for i in range(4):
        for j in range(4):
            t = uv @ s.wave_vectors[i, j].double() + s.wave_phases[i, j].double()
            values = s.wave_amplitudes[i, j].double()[None] * torch.cos(t)[:, None]  # [samples, 3]
            torch.testing.assert_close(mean[i, j].double(), values.mean(0), atol=2e-3, rtol=0)
            std = s.opacities[i].double() * values.std(0).max()
            torch.testing.assert_close(contribution[i, j].double(), std, atol=2e-3, rtol=0)


def mean_colors(s: Surfels) -> torch.Tensor:
    """Each surfel's colour averaged over its Gaussian: base + sum over active waves of a cos(phi) e^{-|k|^2/2}."""
    on = torch.arange(s.num_waves)[None] < (s.wave_counts if s.wave_counts is not None else s.num_waves)[:, None]
    m = torch.cos(s.wave_phases) * torch.exp(-(s.wave_vectors ** 2).sum(-1) / 2) * on
    return s.base_color + (s.wave_amplitudes * m[..., None]).sum(1)


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_pruning_keeps_each_surfels_mean_colour(color_param):
    m = adaptive_model(threshold=0.05, color_param=color_param)
    with torch.no_grad():
        m.wave_freqs.mul_(0.3)  # low frequencies: waves whose mean is far from zero
        m.wave_weights.mul_(10)
        m.wave_weights[:10] *= 0.001  # these surfels lose every wave
    before = mean_colors(m.surfels(CAM))
    first = m.prune_waves(0.05)
    assert first["removed"] > 40 and m.wave_counts[:10].eq(0).all() and m.wave_counts.gt(0).any()
    torch.testing.assert_close(mean_colors(m.surfels(CAM)), before, atol=1e-6, rtol=0)
    # pruning again (new, larger threshold) keeps folding on top of what is folded
    m.prune_waves(0.2)
    torch.testing.assert_close(mean_colors(m.surfels(CAM)), before, atol=1e-6, rtol=0)


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_free_directions_prune_store_and_load_as_they_render(tmp_path, color_param):
    """Waves that learn their direction (wave_freqs [N,width,2]): pruning keeps each surfel's mean colour, and the
    pruned model renders the same after .pt, 8-bit .szp (as its stored copy) and PLY round trips."""
    from splatzoo.export import load_ply, save_ply
    from splatzoo.zoo import stored_copy

    m = adaptive_model(threshold=0.05, color_param=color_param, free_directions=True)
    assert m.wave_freqs.shape[1:] == (4, 2)
    with torch.no_grad():
        m.wave_freqs.mul_(0.3)
        m.wave_freqs[:, :, 1].add_(0.2)  # directions off the fan
        m.wave_weights.mul_(10)
        m.wave_weights[:10] *= 0.001  # these surfels lose every wave
    before = mean_colors(m.surfels(CAM))
    assert m.prune_waves(0.05)["removed"] > 40 and m.wave_counts[:10].eq(0).all() and m.wave_counts.gt(0).any()
    torch.testing.assert_close(mean_colors(m.surfels(CAM)), before, atol=1e-6, rtol=0)
    splatzoo.save_model(m, tmp_path / "m.pt")
    assert torch.equal(render(splatzoo.load_model(tmp_path / "m.pt")).rgb, render(m).rgb)
    assert torch.equal(render(load_ply(save_ply(m, tmp_path / "m.ply"))).rgb, render(m).rgb)
    m.precision = "8bit"
    splatzoo.save_model(m, tmp_path / "m.szp")
    assert torch.equal(render(splatzoo.load_model(tmp_path / "m.szp")).rgb, render(stored_copy(m, "8bit")).rgb)


def counted_model(free: bool):
    """A pruned per-wave model: ten surfels without waves, ten with one, the rest with more."""
    m = adaptive_model(threshold=0.05, color_param="per-wave", free_directions=free)
    with torch.no_grad():
        m.wave_weights.fill_(0.3)
        m.wave_freqs.fill_(0.5)  # a wave of 0.3 then varies the colour by 0.2 (RMS) over its surfel
        m.wave_weights[:10] *= 0.001
        m.wave_weights[10:20, 1:] *= 0.001
        m.wave_weights[20:40, 2:] *= 0.001
    m.prune_waves(0.05)
    assert m.wave_counts.tolist() == [0] * 10 + [1] * 10 + [2] * 20 + [4] * (m.num_primitives - 40)
    return m


@pytest.mark.parametrize("free", [False, True])
def test_wave_counts_are_stored_in_unary_bits_and_older_masks_still_load(tmp_path, free):
    """A checkpoint stores each surfel's wave count in unary (that many ones, then a zero), so a wave-less surfel
    adds one bit to a 2DGS surfel's bytes; only the fan adds each waved surfel's orientations as a bit mask. Files
    written before, with a mask for every surfel, load as they did."""
    m = counted_model(free)
    counts = m.wave_counts
    state = m.checkpoint()["state"]
    code = state["wave_count_bits"]
    assert code.dtype == torch.uint8 and code.numel() == math.ceil((m.num_primitives + int(counts.sum())) / 8)
    assert ("wave_mask" in state) == (not free)
    if not free:
        assert state["wave_mask"].shape == (int(counts.gt(0).sum()),)
    plain = m.stored_row_bytes("8bit")[:10]
    assert torch.equal(plain, torch.full_like(plain, 16 + 1 / 8))  # 2DGS's 16 bytes and one bit
    old = {k: v for k, v in state.items() if k != "wave_count_bits"}  # the layout before: a mask a surfel
    index = m.wave_index.long()
    old["wave_mask"] = torch.where(m.active_slots(), 1 << index, torch.zeros_like(index)).sum(1).to(torch.uint8)
    old["wave_width"] = old["wave_width"].long()
    torch.save({**m.checkpoint(), "state": old}, tmp_path / "old.pt")
    splatzoo.save_model(m, tmp_path / "new.pt")
    for name in ("old.pt", "new.pt"):
        back = splatzoo.load_model(tmp_path / name)
        assert torch.equal(back.wave_counts, counts), name
        assert torch.equal(render(back).rgb, render(m).rgb), name


def _one_wave_more(state):  # counts that give surfel 20 a wave the file does not hold
    from splatzoo.models.gabor import unary_code, unary_counts

    counts = unary_counts(state["wave_count_bits"], state["means"].shape[0], int(state["wave_width"]))
    counts[20] += 1
    return {**state, "wave_count_bits": unary_code(counts)}


@pytest.mark.parametrize("free", [False, True])
@pytest.mark.parametrize("damage, message", [
    (lambda s: {**s, "wave_count_bits": s["wave_count_bits"][:-2]}, "holds counts for"),
    (lambda s: {**s, "wave_count_bits": torch.cat([s["wave_count_bits"], torch.zeros(1, dtype=torch.uint8)])},
     "runs on past the counts"),
    (lambda s: {**s, "wave_count_bits": torch.full_like(s["wave_count_bits"], 255)}, "holds counts for 0 surfels"),
    (lambda s: {**s, "wave_count_bits": s["wave_count_bits"].float()}, "1D uint8 tensor"),
    (lambda s: {**s, "wave_count_bits": torch.full((3, 3), 7, dtype=torch.uint8)}, "1D uint8 tensor"),
    (lambda s: {**s, "wave_width": torch.tensor(1, dtype=torch.uint8)}, "waves but wave_width is 1"),
    (_one_wave_more, "values for the|other wave counts than"),  # the fan's masks see it first
])
def test_damaged_wave_counts_are_refused_by_name(tmp_path, free, damage, message):
    m = counted_model(free)
    ck = m.checkpoint()
    torch.save({**ck, "state": damage(ck["state"])}, tmp_path / "bad.pt")
    with pytest.raises(splatzoo.SplatzooError, match=message):
        splatzoo.load_model(tmp_path / "bad.pt")


@pytest.mark.parametrize("free", [False, True])
def test_orientation_masks_must_match_the_counts(tmp_path, free):
    """The fan's masks are one a waved surfel, each with as many bits as its count; free directions store none."""
    m = counted_model(free)
    ck = m.checkpoint()
    state = dict(ck["state"])
    if free:
        state["wave_mask"] = torch.ones(int(m.wave_counts.gt(0).sum()), dtype=torch.uint8)
        message = "stores wave counts, not orientations"
    else:
        state["wave_mask"] = state["wave_mask"].clone()
        state["wave_mask"][-1] = 1  # one orientation where the counts give four
        message = "other wave counts than wave_count_bits"
        torch.save({**ck, "state": {**state, "wave_mask": state["wave_mask"][:-1]}}, tmp_path / "short.pt")
        with pytest.raises(splatzoo.SplatzooError, match="one orientation mask for each of the"):
            splatzoo.load_model(tmp_path / "short.pt")
    torch.save({**ck, "state": state}, tmp_path / "bad.pt")
    with pytest.raises(splatzoo.SplatzooError, match=message):
        splatzoo.load_model(tmp_path / "bad.pt")


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_waveless_surfels_store_and_train_as_2dgs_surfels(tmp_path, color_param):
    base, diff, extra = COLOR_NAMES[color_param]
    m = adaptive_model(color_param=color_param)
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=0.01, eps=1e-15)
    for _ in range(2):  # moments everywhere
        opt.zero_grad()
        (rasterize(m.surfels(CAM), CAM, backend="cpu").rgb - 0.5).square().sum().backward()
        opt.step()
    with torch.no_grad():
        m.wave_weights[:16] = 1e-6
    m.prune_waves(0.01, opt)
    empty = m.wave_counts == 0
    assert empty[:16].all() and not empty.all()
    waved_only = ((diff,) if diff else ()) + extra
    for name in waved_only:
        assert getattr(m, name)[empty].eq(0).all(), name
    if diff:
        assert opt.state[getattr(m, diff)]["exp_avg"][empty].eq(0).all()
    for _ in range(3):  # a wave-less surfel's wave colour gets no gradient and stays zero
        opt.zero_grad()
        (rasterize(m.surfels(CAM), CAM, backend="cpu").rgb - 0.5).square().sum().backward()
        if diff:
            assert getattr(m, diff).grad[empty].eq(0).all()
        assert getattr(m, base).grad[empty].abs().sum() > 0
        opt.step()
    for name in waved_only:
        assert getattr(m, name)[empty].eq(0).all(), name
    state = m.checkpoint()["state"]
    for name in waved_only:  # only waved surfels store them
        assert state[name].shape[0] == int((~empty).sum()), name
    assert state[base].shape[0] == m.num_primitives and state["wave_mask"].dtype == torch.uint8
    splatzoo.save_model(m, tmp_path / "m.pt")
    back = splatzoo.load_model(tmp_path / "m.pt")
    for name, p in list(m.named_parameters()) + [(name, getattr(m, name)) for name in extra]:
        assert torch.equal(p, getattr(back, name)), name


def test_surfel_with_no_waves_is_a_2dgs_surfel():
    m = adaptive_model()
    with torch.no_grad():
        m.wave_weights[:] = 0.0
    m.prune_waves(0.01)
    assert m.wave_weights.shape[1] == 0 and m.wave_counts.eq(0).all()  # stored width trimmed to nothing
    s = m.surfels(CAM)
    assert s.num_waves == 0
    flat = Surfels.constant_color(s.means, s.quats, s.scales, s.opacities, s.base_color)
    for b in BACKENDS:
        with torch.no_grad():
            assert torch.equal(rasterize(s, CAM, backend=b).rgb, rasterize(flat, CAM, backend=b).rgb)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_packed_checkpoint_round_trip_and_size(tmp_path, backend, color_param):
    full = adaptive_model(color_param=color_param)
    full_path = tmp_path / "full.pt"
    splatzoo.save_model(full, full_path)
    m = adaptive_model(color_param=color_param)
    with torch.no_grad():
        m.wave_weights[::2, 1:] = 0.0
        m.wave_weights[1::4] = 0.0
    m.prune_waves(0.01)
    path = tmp_path / "pruned.pt"
    splatzoo.save_model(m, path)
    assert path.stat().st_size < full_path.stat().st_size and m.size_bytes() < full.size_bytes()
    state = torch.load(path, weights_only=True)["state"]
    assert state["wave_weights"].shape[0] == m.summary()["waves_active"]  # active waves only
    back = splatzoo.load_model(path)
    assert back.config == m.config and torch.equal(back.wave_counts, m.wave_counts)
    a, b = render(m, backend), render(back, backend)
    for k, v in a.tensors().items():
        assert torch.equal(v, getattr(b, k)), k


def test_densify_and_train_with_pruned_waves():
    m = adaptive_model()
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=0.0, eps=1e-15)
    rasterize(m.surfels(CAM), CAM, backend="cpu").rgb.sum().backward()
    opt.step()
    with torch.no_grad():
        m.wave_weights[:40, 2:] = 0.0
    m.prune_waves(0.01, opt)
    # Adam now holds the repacked parameters, with moments of the same shape
    for name in m.wave_parameter_names:
        p = getattr(m, name)
        assert any(p is q for g in opt.param_groups for q in g["params"])
        assert opt.state[p]["exp_avg"].shape == p.shape
    stats = DensifyStats(m.num_primitives)
    stats.grad_sum[:10], stats.count[:10] = 1.0, 1.0
    counts = m.wave_counts.clone()
    res = densify_and_prune(m, opt, stats, grad_threshold=0.5, scene_extent=1.0, min_opacity=0.05,
                            generator=torch.Generator().manual_seed(0))
    assert res["split"] + res["cloned"] == 10 and m.wave_counts.shape == (m.num_primitives,)
    assert m.wave_index.shape == m.wave_weights.shape
    assert torch.equal(m.wave_counts[-20:], counts[:10].repeat(2))  # split children inherit their waves
    opt.zero_grad()
    rasterize(m.surfels(CAM), CAM, backend="cpu").rgb.sum().backward()
    opt.step()


def test_trainer_prunes_through_the_hook(tmp_path):
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    data = make_synthetic_scene("plain", tmp_path / "plain", views=6, width=32, height=32)
    cfg = TrainConfig(iterations=60, num_primitives=150, densify=False, log_every=10, eval_every=60)
    res = train(data, "gabor", {"prune_waves": 0.02, "prune_from": 0.3}, cfg, tmp_path / "run", progress=False,
                evaluate_at_end=False)
    m = res.model
    assert m.summary()["waves_active"] < 150 * 4
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    fractions = [r["wave_fraction"] for r in log if "wave_fraction" in r]
    assert fractions[0] == 1.0 and fractions[-1] < 1.0
    back = splatzoo.load_model(tmp_path / "run" / "model.pt")
    assert torch.equal(render(back, "cpu").rgb, render(m.cpu(), "cpu").rgb)


def test_relative_threshold_follows_the_training_error(tmp_path):
    """prune_relative: the threshold is that fraction of the trainer's recent mean absolute error, which the
    checkpoint keeps (a resumed run prunes as the uninterrupted one would)."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import Run, train
    from splatzoo.training import TrainConfig

    with pytest.raises(ShapeError, match="one pruning criterion"):
        splatzoo.create_model("gabor", prune_waves=0.01, prune_relative=0.2)
    with pytest.raises(ShapeError, match="prune_relative"):
        splatzoo.create_model("gabor", prune_relative=-1.0)
    m = adaptive_model(threshold=0.0, prune_relative=0.5)
    assert m.adaptive and m.prune_threshold() == 0.0  # nothing measured yet: nothing pruned
    m.recent_error = 0.04
    assert m.prune_threshold() == pytest.approx(0.02)

    data = make_synthetic_scene("plain", tmp_path / "plain", views=6, width=32, height=32)
    cfg = TrainConfig(iterations=60, num_primitives=150, densify=False, log_every=10, eval_every=60)
    res = train(data, "gabor", {"prune_relative": 0.5, "prune_from": 0.3}, cfg, tmp_path / "run", progress=False,
                evaluate_at_end=False)
    error = res.model.recent_error
    assert 0.001 < error < 0.5 and res.model.summary()["waves_active"] < 150 * 4
    state = Run(tmp_path / "run").checkpoint()
    assert state["recent_error"] == pytest.approx(error)


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_a_trial_removal_renders_what_pruning_leaves(color_param):
    """prune_psnr measures a pruning before making it: the trial surfels render as the pruned model does."""
    m = adaptive_model(threshold=0.0, prune_psnr=0.05, color_param=color_param)
    with torch.no_grad():
        m.wave_freqs.mul_(0.3)  # waves with a visible mean, which the base colour must take over
        m.wave_weights[:10] *= 0.001  # these surfels lose every wave
    mean, contribution = m.wave_statistics()
    threshold = float(contribution.median())
    trial = m._surfels_without(CAM, m.active_slots() & (contribution < threshold), mean)
    with torch.no_grad():
        expected = rasterize(trial, CAM, backend="reference").rgb
    assert m.prune_waves(threshold)["removed"] > 0 and m.wave_counts[:10].eq(0).all()
    torch.testing.assert_close(render(m).rgb, expected, atol=1e-5, rtol=0)


def test_measured_threshold_removes_what_costs_nothing_and_keeps_what_costs():
    """Half the waves are zero: removing them costs no PSNR, removing any other costs more than the tolerance, so
    the bisection removes exactly the zero waves; with a generous tolerance it removes everything."""
    m = adaptive_model(threshold=0.0, prune_psnr=0.01)
    with torch.no_grad():
        m.wave_weights[:, 2:] = 0.0
        m.wave_weights[:, :2] = 0.5 + m.wave_weights[:, :2]  # clearly visible
        target = render(m).rgb + 0.01  # an error the waves do not explain
    calls = []

    def probe_error(surfels_of):
        calls.append(1)
        with torch.no_grad():
            return float((rasterize(surfels_of(CAM), CAM, backend="cpu").rgb - target).square().mean())

    m.probe_error = probe_error
    before = probe_error(m.surfels)
    assert m.measured_threshold(0.01) > 0 and len(calls) <= 1 + 1 + 7  # the reference and the bisection's trials
    removed = m.prune_waves(m.measured_threshold(0.01))["removed"]
    # every zero wave goes, and of the others only those that cost nothing (on surfels the camera does not see)
    assert removed >= 64 * 2 and m.wave_counts.le(2).all() and m.wave_counts.sum() > 64
    assert 10 * math.log10(probe_error(m.surfels) / before) <= 0.01
    m.prune_waves(m.measured_threshold(100.0))
    assert m.wave_counts.eq(0).all()
    with pytest.raises(ShapeError, match="prune_psnr"):
        splatzoo.create_model("gabor", prune_psnr=-0.1)


def test_trainer_prunes_by_measured_cost(tmp_path):
    """prune_psnr in training: the trainer's probe views price each pruning; a tiny budget keeps visible waves that a
    large one removes."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    data = make_synthetic_scene("sweater", tmp_path / "sweater", views=6, width=32, height=32)
    cfg = TrainConfig(iterations=80, num_primitives=150, densify=False, log_every=10, eval_every=80)
    kept = {}
    for budget in (1e-4, 30.0):
        res = train(data, "gabor", {"prune_psnr": budget, "prune_from": 0.5}, cfg, tmp_path / f"run{budget}",
                    progress=False, evaluate_at_end=False)
        kept[budget] = res.model.summary()["waves_active"]
    assert kept[30.0] == 0 and kept[1e-4] > 0


# ---- view-dependent colour --------------------------------------------------------------------------------------

def test_gabor_sh_is_view_dependent():
    pts, cols = point_cloud(8)
    m = splatzoo.create_model("gabor", pts, cols, sh_degree=2)
    assert m.sh_rest.shape == (8, 8, 3)
    other = Camera.look_at([3.5, 0.0, 0.0], [0.0, 0.0, 0.0], width=32, height=32)
    assert torch.allclose(m.surfels(CAM).base_color, m.surfels(other).base_color)  # SH starts at zero
    with torch.no_grad():
        m.sh_rest.normal_(0, 0.3)
    assert not torch.allclose(m.surfels(CAM).base_color, m.surfels(other).base_color)
    plain = splatzoo.create_model("gabor", pts, cols)
    assert "sh_rest" not in dict(plain.named_parameters())  # the paper's model is unchanged
    names = [g["name"] for g in m.optim_groups(1.0)]
    assert "sh_rest" in names


def test_adaptive_sh_gabor_is_conformant(tmp_path):
    """What tests/test_models.py checks for every registered model, for the new options."""
    m = adaptive_model(sh_degree=1)
    out = rasterize(m.surfels(CAM), CAM, backend="reference")
    (out.rgb - 0.3).abs().mean().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    splatzoo.save_model(m, tmp_path / "m.pt")
    back = splatzoo.load_model(tmp_path / "m.pt")
    assert torch.equal(render(m).rgb, render(back).rgb)


@pytest.mark.parametrize("weights", ["some", "none"])
@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_pruned_model_ply_round_trip(tmp_path, weights, color_param):
    """The PLY holds the trimmed width (down to no wave columns at all); load_ply reads the width from the file."""
    from splatzoo.export import load_ply, save_ply

    m = adaptive_model(color_param=color_param)
    with torch.no_grad():
        m.wave_weights[:, 2:] = 0.0
        m.wave_weights[::3, :] = 0.0
        if weights == "none":
            m.wave_weights[:] = 0.0
    m.prune_waves(0.01)
    width = m.wave_weights.shape[1]
    assert 0 < width <= 2 if weights == "some" else width == 0
    back = load_ply(save_ply(m, tmp_path / "m.ply"))
    assert torch.equal(back.wave_counts, m.wave_counts) and torch.equal(back.wave_index, m.wave_index)
    assert torch.equal(render(back).rgb, render(m).rgb)


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_adaptive_gabor_is_gabor_until_the_first_pruning(color_param):
    pts, cols = point_cloud()
    plain = splatzoo.create_model("gabor", pts, cols, seed=1, color_param=color_param)
    adaptive = splatzoo.create_model("gabor", pts, cols, seed=1, prune_waves=0.01, color_param=color_param)
    assert dict(plain.named_parameters()).keys() == dict(adaptive.named_parameters()).keys()  # nothing extra to train
    for name, p in plain.named_parameters():
        assert torch.equal(p, getattr(adaptive, name)), name
    assert torch.equal(render(plain).rgb, render(adaptive).rgb)
    # and stays bit-identical through training steps (a rounding difference would grow chaotically)
    opts = [torch.optim.Adam(m.optim_groups(1.0), lr=0.01, eps=1e-15) for m in (plain, adaptive)]
    for _ in range(3):
        for m, opt in zip((plain, adaptive), opts):
            opt.zero_grad()
            (rasterize(m.surfels(CAM), CAM, backend="cpu").rgb - 0.4).square().sum().backward()
            opt.step()
    for name, p in plain.named_parameters():
        assert torch.equal(p, getattr(adaptive, name)), name


def test_checkpoints_of_the_single_fold_format_still_load():
    """fixtures/adaptive_v010.pt was saved by splatzoo 0.1.0 (one folded weight on (cA + cB)/2; color_b stored for
    every surfel); its render, by the code of that release, is adaptive_v010_render.pt."""
    from pathlib import Path

    fixtures = Path(__file__).parent / "fixtures"
    m = splatzoo.load_model(fixtures / "adaptive_v010.pt")
    assert m.wave_counts.eq(0).sum() == 12 and m.color_b[:12].eq(0).all()
    torch.testing.assert_close(render(m).rgb, torch.load(fixtures / "adaptive_v010_render.pt"), atol=1e-6, rtol=0)
