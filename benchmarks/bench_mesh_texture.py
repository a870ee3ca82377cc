"""How close a textured TSDF mesh comes to the model it was baked from, against the vertex-coloured mesh.

Make a run, then mesh and score it (CPU, a few minutes on 2 cores):

    nice -n 10 env OMP_NUM_THREADS=1 splatzoo synth sweater --out /tmp/tmesh/data --views 24 --width 128 --height 128
    nice -n 10 env OMP_NUM_THREADS=1 splatzoo train /tmp/tmesh/data --model gabor --iterations 1500 --out /tmp/tmesh/gabor
    nice -n 10 env OMP_NUM_THREADS=1 python benchmarks/bench_mesh_texture.py /tmp/tmesh/gabor
    nice -n 10 env OMP_NUM_THREADS=1 python benchmarks/bench_mesh_texture.py /tmp/tmesh/gabor --voxel-scale 1

The second run meshes with extract-mesh's own voxel (half a pixel; 254k triangles, simplified to 50k for the
atlas).

The mesh is extracted once from the training views, with the export's voxel (2 x extract-mesh's default, about a
pixel; --voxel-size sets it), and textured from the same views; the test views (never used for baking) are then
rendered three ways: the model itself, the vertex-coloured mesh and the textured mesh (ray cast with 2 x 2 rays per
pixel, unlit; `splatzoo.mesh_texture.render_mesh`), all over the scene's background. A mesh above --max-triangles
is also scored with vertex colours after the same simplification the texture gets. PSNR is taken over the object
pixels: where the model's alpha (>= 0.5) or the mesh's coverage says there is an object ("object": holes and
silhouette differences of the mesh count), and over the pixels where both do ("both": the colour alone). "vs model"
compares a mesh render with the model's render, "vs truth" with the test image; the model's own PSNR against the
truth is printed for scale. The textured GLB is written and read back (trimesh) before scoring, so the numbers are
those of the file.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from splatzoo.mesh_texture import TexturedMesh, TexturedMeshOptions, render_mesh, texture_mesh, write_glb  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    mse = float(((a[mask] - b[mask]) ** 2).mean())
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def read_glb(path: Path):
    """A TexturedMesh back from our GLB (through trimesh, an independent reader)."""
    import trimesh

    tm = trimesh.load(path, force="mesh", process=False)
    img = np.asarray(tm.visual.material.baseColorTexture.convert("RGB"))
    uv = np.asarray(tm.visual.uv, dtype=np.float32).copy()
    uv[:, 1] = 1.0 - uv[:, 1]          # trimesh flips v to the OBJ convention on load
    return TexturedMesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int64), uvs=uv, texture=img)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--texture-size", type=int, default=2048)
    ap.add_argument("--max-triangles", type=int, nargs="+", default=[50000])
    ap.add_argument("--sharpness", type=float, nargs="+", default=[1.0])
    ap.add_argument("--render-scale", type=float, nargs="+", default=[1.0])
    ap.add_argument("--samples", type=int, default=2, help="rays per pixel side when rendering the meshes")
    ap.add_argument("--voxel-size", type=float, help="TSDF voxel (default: --voxel-scale x extract-mesh's)")
    ap.add_argument("--voxel-scale", type=float, default=TexturedMeshOptions.voxel_scale,
                    help="voxel as a multiple of extract-mesh's default (the export's default)")
    ap.add_argument("--no-vertex", action="store_true", help="skip the vertex-coloured mesh")
    ap.add_argument("--save", type=Path, help="folder for the comparison images of the first test view")
    args = ap.parse_args()

    from splatzoo.mesh import extract_mesh, mesh_parameters
    from splatzoo.runs import Run

    torch.set_num_threads(1)
    model, scene, _ = Run(args.run).load("auto")
    train = [v.camera for v in scene.train]
    tests = scene.test
    bg = np.asarray(scene.background, np.float32)
    t0 = time.perf_counter()
    voxel = args.voxel_size or args.voxel_scale * mesh_parameters(train).voxel_size
    mesh, params, stats = extract_mesh(model, train, voxel_size=voxel)
    print(f"TSDF mesh: {stats.vertices} vertices, {stats.triangles} triangles, voxel {params.voxel_size:.4g} "
          f"({time.perf_counter() - t0:.1f} s); {len(train)} training views baked, {len(tests)} test views scored")
    vc = TexturedMesh.from_open3d(mesh)

    refs = []
    with torch.no_grad():
        for v in tests:
            out = model.render(v.camera, background=torch.as_tensor(bg, device=next(model.parameters()).device),
                               image_only=True)
            refs.append((out.rgb.clamp(0, 1).cpu().numpy(), out.alpha.cpu().numpy() >= 0.5,
                         v.image_float() if hasattr(v, "image_float") else v.image() / 255.0))

    def score(m, name):
        rows = {"object": ([], [], []), "both": ([], [], [])}
        for (ref, alpha, gt), v in zip(refs, tests):
            img, hit = render_mesh(m, v.camera, background=bg, samples=args.samples)
            gt = np.asarray(gt, np.float32)
            for key, mask in (("object", alpha | hit), ("both", alpha & hit)):
                pm, pt, pgt = rows[key]
                pm.append(psnr(img, ref, mask))
                pt.append(psnr(img, gt, mask))
                pgt.append(psnr(ref, gt, mask))
        print(name)
        for key, (pm, pt, pgt) in rows.items():
            print(f"    {key:<7s} pixels: vs model {np.mean(pm):6.2f} dB   vs truth {np.mean(pt):6.2f} dB   "
                  f"(model vs truth {np.mean(pgt):6.2f} dB)")

    if not args.no_vertex:
        score(vc, f"vertex colours ({len(vc.faces)} triangles)")
    with tempfile.TemporaryDirectory() as tmp:
        for tris in args.max_triangles:
            atlas = None
            if tris and tris < len(vc.faces):
                small = TexturedMesh.from_open3d(mesh.simplify_quadric_decimation(tris))
                score(small, f"vertex colours, simplified to {len(small.faces)} triangles")
            for sharp in args.sharpness:
                for rs in args.render_scale:
                    t0, c0 = time.perf_counter(), time.process_time()
                    # the first bake makes the atlas; the others bake again into its UVs
                    tex = texture_mesh(atlas if atlas is not None else mesh, model, train,
                                       dict(texture_size=args.texture_size, sharpness=sharp, render_scale=rs,
                                            max_triangles=tris),
                                       progress=lambda msg: print("    " + msg, flush=True))
                    atlas = atlas if atlas is not None else tex
                    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
                    path = write_glb(tex, Path(tmp) / "mesh.glb")
                    back = read_glb(path)
                    score(back, f"texture {args.texture_size}, {tex.info['triangles']} triangles, sharpness {sharp:g}, "
                          f"render scale {rs:g} ({secs:.0f} s, {cpu:.0f} s CPU)")
                    print(f"    {tex.info['surface_seen']:.1%} of the surface seen, "
                          f"{tex.info['mean_views_per_texel']:.1f} views per texel, "
                          f"GLB {path.stat().st_size / 1e6:.1f} MB")
        if args.save:
            from PIL import Image

            args.save.mkdir(parents=True, exist_ok=True)
            ref, _, gt = refs[0]
            a, _ = render_mesh(vc, tests[0].camera, background=bg, samples=args.samples)
            b, _ = render_mesh(back, tests[0].camera, background=bg, samples=args.samples)
            row = np.concatenate([np.asarray(gt, np.float32), ref, a, b], 1)
            Image.fromarray((np.clip(row, 0, 1) * 255).round().astype(np.uint8)).resize(
                (row.shape[1] * 2, row.shape[0] * 2), Image.NEAREST).save(args.save / "mesh_texture.png")
            Image.fromarray(back.texture).save(args.save / "texture.png")
            print(f"wrote {args.save / 'mesh_texture.png'} (truth, model, vertex colours, texture)")


if __name__ == "__main__":
    main()
