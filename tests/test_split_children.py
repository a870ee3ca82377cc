"""Split children keep their parent's pattern: a child drawn by densification's split_rows shows, at every point of
its plane, the colour its parent showed at the same world point (waves rescaled and shifted, textures resampled)."""
import copy
import math

import pytest
import torch

import splatzoo
from splatzoo.geometry import quat_to_rotmat
from splatzoo.rasterizers.reference import _appearance_color, _texture_sample
from splatzoo.training.densify import SPLIT_SHRINK, split_rows
from splatzoo.types import TEXTURE_RADIUS, Camera

N = 3  # parents, each split into two children
# far away: the view direction (spherical harmonics) is the same for a parent and its children
CAMERA = Camera.look_at((0.0, 0.0, -1e6), (0.0, 0.0, 0.0))


def patterned(name: str, seed: int = 0, **options):
    """N surfels of model `name` (float64) with strong random appearance over (u, v)."""
    g = torch.Generator().manual_seed(seed)
    m = splatzoo.create_model(name, torch.randn(N, 3, generator=g), torch.rand(N, 3, generator=g), **options).double()
    with torch.no_grad():
        m.quats.copy_(torch.randn(N, 4, generator=g))
        m.log_scales.copy_(torch.randn(N, 2, generator=g) * 0.5 - 1)
        if hasattr(m, "wave_freqs"):
            shape = m.wave_freqs.shape[:2]  # [N, K] slots (free directions store a 2D vector a slot)
            m.wave_freqs.copy_(4 * torch.rand(m.wave_freqs.shape, generator=g) - 2)  # up to 2 cycles per sigma
            m.wave_weights.copy_(0.5 + torch.rand(m.wave_weights.shape, generator=g))  # per-wave: an RGB amplitude
            if m.learn_phase:
                m.wave_phases.copy_(2 * math.pi * torch.rand(shape, generator=g) - math.pi)
            for colour in ("color_base", "color_a"):
                if hasattr(m, colour):
                    getattr(m, colour).copy_(5 + torch.rand(N, 3, generator=g))  # above every wave sum: no clamping
            for colour in ("color_diff", "color_b"):
                if hasattr(m, colour):
                    getattr(m, colour).copy_(0.5 * torch.rand(N, 3, generator=g))
        if hasattr(m, "sh_rest"):
            m.sh_rest.copy_(0.3 * torch.randn(m.sh_rest.shape, generator=g))
        if hasattr(m, "texture_rgb"):
            m.texture_rgb.copy_(0.4 * torch.randn(m.texture_rgb.shape, generator=g))
            m.texture_alpha_logit.copy_(2 * torch.randn(m.texture_alpha_logit.shape, generator=g))
        if hasattr(m, "sh_dc"):
            m.sh_dc.add_(2)  # no clamping at 0
    return m


def split(m, seed: int = 7):
    """(children model, parent index per child [2N])."""
    idx = torch.arange(N).repeat(2)
    params = {k: v.detach() for k, v in m.per_primitive().items()}
    children = split_rows(m, params, idx, torch.Generator().manual_seed(seed))
    c = copy.deepcopy(m)
    c.replace_parameters(children)
    return c, idx


def parent_coordinates(m, c, idx, u, v):
    """(u, v) [P,2N] on the children's planes -> the same world points in their parents' (u, v), from the geometry
    alone (means, rotations, scales), checking that the points lie on the parents' planes."""
    s_c, s_p = torch.exp(c.log_scales.detach()), torch.exp(m.log_scales.detach())[idx]
    R_c, R_p = quat_to_rotmat(c.quats.detach()), quat_to_rotmat(m.quats.detach())[idx]
    world = c.means.detach() + u[..., None] * (R_c[:, :, 0] * s_c[:, :1]) + v[..., None] * (R_c[:, :, 1] * s_c[:, 1:])
    local = torch.einsum("nji,pnj->pni", R_p, world - m.means.detach()[idx])  # R_p^T (x - mean)
    assert local[..., 2].abs().max() < 1e-9  # the child lies on its parent's plane
    return local[..., 0] / s_p[:, 0], local[..., 1] / s_p[:, 1]


@torch.no_grad()
def colour(m, idx, u, v):
    """(colour [P,n,3], texture sample [P,n,4] or None) of surfels idx at (u, v) [P,n], as the reference shades."""
    s = m.surfels(CAMERA)
    tex = _texture_sample(s, idx, u, v)
    return _appearance_color(s, idx, u, v, tex=tex), tex


EXACT = [("2dgs", {}), ("2dgs", {"sh_degree": 2}), ("gabor", {}), ("gabor", {"color_param": "paper"}),
         ("gabor", {"sh_degree": 2}), ("gabor", {"n_waves": 6}), ("baseline-a", {}), ("baseline-b", {}),
         ("gabor-adaptive", {}), ("gabor-adaptive", {"color_param": "paper"}), ("gabor", {"color_param": "per-wave"}),
         ("beta-gabor", {"color_param": "per-wave"}), ("gabor", {"free_directions": True}),
         ("beta-gabor", {"free_directions": True})]


@pytest.mark.parametrize("name,options", EXACT, ids=[n + "".join(f"-{k}={v}" for k, v in o.items()) for n, o in EXACT])
def test_wave_children_show_their_parents_colour_at_the_same_world_points(name, options):
    m = patterned(name, **options)
    if getattr(m, "adaptive", False):
        _, contribution = m.wave_statistics()
        m.prune_waves(float(contribution.median()))  # counts differ per surfel, slots hold other orientations
        assert len(set(m.wave_counts.tolist())) > 1 and bool((m.wave_index != torch.arange(
            m.wave_index.shape[1])).any())
    c, idx = split(m)
    g = torch.Generator().manual_seed(3)
    u, v = 2 * torch.randn(2, 200, 2 * N, generator=g, dtype=torch.float64)
    pu, pv = parent_coordinates(m, c, idx, u, v)
    child, _ = colour(c, torch.arange(2 * N), u, v)
    parent, _ = colour(m, idx, pu, pv)
    if hasattr(m, "wave_freqs"):
        assert parent.std(0).max() > 0.1  # a pattern to keep
    torch.testing.assert_close(child, parent, rtol=0, atol=1e-6)


def test_without_the_split_hook_a_child_shows_the_pattern_too_coarse():
    """The check above can fail: children that keep their parent's waves do not show its colour."""
    m = patterned("gabor")
    c, idx = split(m)
    plain = copy.deepcopy(c)
    with torch.no_grad():  # the parent's waves, unchanged
        plain.wave_freqs.copy_(m.wave_freqs[idx])
        plain.wave_phases.copy_(m.wave_phases[idx])
    u, v = torch.randn(2, 200, 2 * N, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    pu, pv = parent_coordinates(m, c, idx, u, v)
    wrong = (colour(plain, torch.arange(2 * N), u, v)[0] - colour(m, idx, pu, pv)[0]).abs().max()
    assert wrong > 0.1


@pytest.mark.parametrize("options", [{}, {"color_param": "paper", "prune_waves": 0.01}, {"color_param": "per-wave"}],
                         ids=["residual", "paper", "per-wave"])
def test_baseline_c_children_keep_the_mean_and_fit_the_pattern_best_without_a_phase(options):
    """Baseline C has no phase to shift: each child's wave is the zero-phase wave closest to its parent's over the
    child's Gaussian (weight w cos(k.offset)), with the child's mean colour exactly the parent pattern's there."""
    m = patterned("baseline-c", **options)
    c, idx = split(m)
    x = torch.linspace(-7, 7, 281, dtype=torch.float64)
    gu, gv = torch.meshgrid(x, x, indexing="ij")
    weight = torch.exp(-(gu ** 2 + gv ** 2) / 2).reshape(-1, 1, 1)
    weight = weight / weight.sum()
    u, v = gu.reshape(-1, 1).expand(-1, 2 * N), gv.reshape(-1, 1).expand(-1, 2 * N)
    pu, pv = parent_coordinates(m, c, idx, u, v)
    parent = colour(m, idx, pu, pv)[0]
    child = colour(c, torch.arange(2 * N), u, v)[0]
    torch.testing.assert_close((weight * child).sum(0), (weight * parent).sum(0), rtol=0, atol=1e-7)
    plain = copy.deepcopy(c)  # frequencies rescaled, weights (and folded weights) as the parent's
    with torch.no_grad():
        plain.wave_weights.copy_(m.wave_weights[idx])
        if hasattr(plain, "folded_weights"):
            plain.folded_weights.copy_(m.folded_weights[idx])
    kept = colour(plain, torch.arange(2 * N), u, v)[0]
    error, error_kept = ((weight * (child - parent) ** 2).sum(0), (weight * (kept - parent) ** 2).sum(0))
    assert bool((error <= error_kept + 1e-12).all()) and float(error.sum()) < 0.9 * float(error_kept.sum())


def bilinear_oracle(texture: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """texture [T,T,C] at (u, v) [P] by grid_sample: texel centres at -R + (c + 1/2) 2R/T are align_corners=False's,
    the border padding is the edge clamp."""
    grid = torch.stack([u, v], -1)[None, None] / TEXTURE_RADIUS  # [1,1,P,2], x = u (columns), y = v (rows)
    out = torch.nn.functional.grid_sample(texture.permute(2, 0, 1)[None], grid, mode="bilinear",
                                          padding_mode="border", align_corners=False)
    return out[0, :, 0].T  # [P,C]


@pytest.mark.parametrize("size", [1, 4, 5])
def test_a_textured_childs_texels_are_its_parents_bilinear_samples_at_their_centres(size):
    m = patterned("textured", texture_size=size)
    c, idx = split(m)
    centres = -TEXTURE_RADIUS + (torch.arange(size, dtype=torch.float64) + 0.5) * (2 * TEXTURE_RADIUS / size)
    v, u = (t.reshape(-1) for t in torch.meshgrid(centres, centres, indexing="ij"))  # texel (r, c) row-major
    pu, pv = parent_coordinates(m, c, idx, u[:, None].expand(-1, 2 * N), v[:, None].expand(-1, 2 * N))
    for i in range(2 * N):
        p = int(idx[i])
        rgba = torch.cat([m.texture_rgb[p], torch.sigmoid(m.texture_alpha_logit[p])], -1).detach()
        want = bilinear_oracle(rgba, pu[:, i], pv[:, i]).reshape(size, size, 4)
        torch.testing.assert_close(c.texture_rgb[i].detach(), want[..., :3], rtol=0, atol=1e-9)
        torch.testing.assert_close(torch.sigmoid(c.texture_alpha_logit[i].detach()), want[..., 3:], rtol=0,
                                   atol=1.1e-6)  # alpha clamped to [1e-6, 1 - 1e-6]
    assert torch.isfinite(c.texture_alpha_logit).all()
    if size > 1:  # a texture that did not follow its child would fail the check
        assert (c.texture_rgb.detach() - m.texture_rgb.detach()[idx]).abs().max() > 0.05


def test_textured_children_show_their_parents_colour_and_alpha():
    """At the child's texel centres exactly, for a random texture; everywhere on the child, for a texture linear in
    (u, v) and a child inside the texel centres' square (bilinear resampling is exact for a linear function)."""
    m = patterned("textured")
    c, idx = split(m)
    size = m.config.texture_size
    centres = -TEXTURE_RADIUS + (torch.arange(size, dtype=torch.float64) + 0.5) * (2 * TEXTURE_RADIUS / size)
    v, u = (t.reshape(-1, 1).expand(-1, 2 * N) for t in torch.meshgrid(centres, centres, indexing="ij"))
    pu, pv = parent_coordinates(m, c, idx, u, v)
    (child, child_tex), (parent, parent_tex) = colour(c, torch.arange(2 * N), u, v), colour(m, idx, pu, pv)
    torch.testing.assert_close(child, parent, rtol=0, atol=1e-9)
    torch.testing.assert_close(child_tex[..., 3], parent_tex[..., 3], rtol=0, atol=1.1e-6)

    with torch.no_grad():  # a linear texture over the texel centres
        slope = torch.randn(N, 2, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 0.2
        cu, cv = torch.meshgrid(centres, centres, indexing="xy")  # [T,T]: texel (r, c) at u = centres[c]
        m.texture_rgb.copy_(cu[None, ..., None] * slope[:, None, None, 0]
                            + cv[None, ..., None] * slope[:, None, None, 1])
        m.texture_alpha_logit.fill_(2.0)
    margin = TEXTURE_RADIUS - TEXTURE_RADIUS / size  # the outermost texel centres
    checked = 0
    for seed in range(20):  # the children that lie within their parent's texel centres
        c, idx = split(m, seed)
        u, v = (2 * torch.rand(2, 300, 2 * N, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
                - 1) * margin
        pu, pv = parent_coordinates(m, c, idx, u, v)
        corners = torch.tensor([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]], dtype=torch.float64) * margin
        cu, cv = parent_coordinates(m, c, idx, *(t[:, None].expand(-1, 2 * N) for t in corners.T))
        inside = (cu.abs().amax(0) <= margin) & (cv.abs().amax(0) <= margin)  # the child's texel centres' square
        child, parent = colour(c, torch.arange(2 * N), u, v)[0], colour(m, idx, pu, pv)[0]
        assert parent.std(0).max() > 0.05
        torch.testing.assert_close(child[:, inside], parent[:, inside], rtol=0, atol=1e-9)
        checked += int(inside.sum())
    assert checked >= 10


def test_split_rows_shrinks_the_children_as_2dgs():
    m = patterned("gabor")
    c, idx = split(m)
    torch.testing.assert_close(c.log_scales, m.log_scales[idx] - math.log(SPLIT_SHRINK))
