"""Fuzzing every loader and the command line's option parsing with seeded mutations of small valid inputs.

Each case mutates a valid seed file (bit flips, truncation, inserted or duplicated bytes, huge counts, NaN and
infinity, wrong types, deleted keys, deep nesting, ...), hands it to the public loader and asserts one of two
outcomes: a SplatzooError (a named refusal), or a result that is really valid (a model with finite parameters that
renders, a scene whose cameras pass and whose images decode, a resumed run whose model is finite). Any other
exception, or a case running past CASE_SECONDS, fails with the case id, what was mutated and the traceback.

The targets: our model files (PLY, model.pt), checkpoints and run records; the datasets (COLMAP, transforms.json and
its lens distortion, images, point clouds); third-party PLY layouts and the splat formats read through
splat-transform (.spz, .sog, .splat, .ksplat); `train --init-from` a damaged file (refused: no run folder left);
option strings (`model:key=value`, `format:key=value`); `bench` with its options (the benchmarks replaced by
recorders: everything is checked before anything runs); and the command line, where a refused command, `train
--overwrite` into a finished run included, must leave every existing file byte-identical.

Cases are deterministic: case `ply-binary-17` always makes the same mutation (random.Random("ply-binary-17")), so
`pytest tests/test_fuzz.py -k ply-binary-17` reproduces a failure. By default each target gets DEFAULT_CASES cases
(the whole file runs in CI in well under 2 minutes); after changing a loader run more with

    python -m pytest -q tests/test_fuzz.py --fuzz-cases 300     # 300 mutated inputs per target

The "known cases" at the end are regressions for inputs that were once accepted silently or crashed.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import random
import re
import shutil
import signal
import struct
import traceback
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from splatzoo.errors import SplatzooError

DEFAULT_CASES = 50
CASE_SECONDS = 10.0

TARGETS = ("ply-binary", "ply-ascii", "model-pt", "checkpoint", "run-config", "colmap-bin", "colmap-txt",
           "blender-json", "images", "points-ply", "cli", "ply-variants", "splat-formats", "distortion",
           "init-from", "option-strings", "refused-train", "bench")


def pytest_generate_tests(metafunc):
    if "fuzz_case" in metafunc.fixturenames:
        n = metafunc.config.getoption("fuzz_cases") or DEFAULT_CASES
        ids = [f"{target}-{i}" for target in TARGETS for i in range(n)]
        metafunc.parametrize("fuzz_case", ids, ids=ids)


# --- running one case --------------------------------------------------------------------------------------------

class Hang(BaseException):
    """Raised by the alarm: a BaseException, so no loader's `except Exception` can swallow it."""


@contextmanager
def deadline(seconds: float):
    def on_alarm(signum, frame):
        raise Hang(f"still running after {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(case: str, what: str, load, validate=None):
    """Run `load()` (then `validate(result)`) under the deadline: a SplatzooError or a valid result pass, anything
    else fails the test naming the case, the mutation and the traceback. Returns the result (None if refused)."""
    try:
        with deadline(CASE_SECONDS):
            result = load()
            if validate is not None:
                validate(result)
        return result
    except SplatzooError:
        return None
    except Hang as e:
        pytest.fail(f"{case} ({what}): {e}: a hang", pytrace=False)
    except Exception:  # noqa: BLE001 -- the point of the test: name anything that is not a SplatzooError
        pytest.fail(f"{case} ({what}): not a SplatzooError\n{traceback.format_exc()}", pytrace=False)


# --- mutators ----------------------------------------------------------------------------------------------------

def _offset(rng: random.Random, size: int, hot: int | None = None) -> int:
    """A position in a file of `size` bytes; half the time within the first `hot` bytes (the header)."""
    if size <= 0:
        return 0
    if hot and rng.random() < 0.5:
        return rng.randrange(min(hot, size))
    return rng.randrange(size)


def mutate_bytes(rng: random.Random, data: bytes, hot: int | None = None) -> tuple[bytes, str]:
    """One of: bit flips, a run of 0x00 or 0xFF, truncation, inserted random bytes, a duplicated chunk."""
    kind = rng.choice(["bitflip", "overwrite", "truncate", "insert", "duplicate"])
    b = bytearray(data)
    if kind == "bitflip":
        flips = rng.randint(1, 8)
        for _ in range(flips):
            i = _offset(rng, len(b), hot)
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b), f"{flips} bit flip(s)"
    if kind == "overwrite":
        i, n, v = _offset(rng, len(b), hot), rng.randint(1, 8), rng.choice([0x00, 0xFF])
        b[i:i + n] = bytes([v]) * len(b[i:i + n])
        return bytes(b), f"{n} bytes at {i} set to {v:#04x}"
    if kind == "truncate":
        i = _offset(rng, len(b), hot)
        return bytes(b[:i]), f"truncated to {i} bytes"
    if kind == "insert":
        i, n = _offset(rng, len(b), hot), rng.randint(1, 16)
        return bytes(b[:i]) + rng.randbytes(n) + bytes(b[i:]), f"{n} random bytes inserted at {i}"
    i = _offset(rng, len(b), hot)
    n = rng.randint(1, 64)
    return bytes(b[:i + n]) + bytes(b[i:i + n]) + bytes(b[i + n:]), f"{n} bytes at {i} duplicated"


# values a hand edit, a bug or an attacker might leave in a JSON or pickled field
SPECIAL = [float("nan"), float("inf"), float("-inf"), 1e308, -1e308, 5e-324, -1, 0, 1, 2**31, 2**63, -2**63,
           10**30, 10**400, 0.5, "x", "", "nan", "1", None, True, False, [], {}, [1, 2, 3], {"a": 1}, [[[]]],
           "a" * 5000]


def _nodes(doc, path=()):
    """Paths to every node below the root of a JSON-like tree (tensors are leaves)."""
    if isinstance(doc, dict):
        items = list(doc.items())
    elif isinstance(doc, (list, tuple)):
        items = list(enumerate(doc))
    else:
        return
    for k, v in items:
        yield path + (k,)
        yield from _nodes(v, path + (k,))


def _parent(doc, path):
    for k in path[:-1]:
        doc = doc[k]
    return doc


def _set(doc, path, value):
    parent = _parent(doc, path)
    if isinstance(parent, tuple):  # tuples inside a checkpoint (Adam's betas): rebuild the tuple
        grand = _parent(doc, path[:-1])
        items = list(parent)
        items[path[-1]] = value
        grand[path[-2]] = tuple(items)
    else:
        parent[path[-1]] = value


BOMB = "\x00NESTING-BOMB\x00"


def mutate_tree(rng: random.Random, doc, *, tensors: bool = False) -> tuple[object, str]:
    """A deep-copied `doc` with one node replaced, deleted, nested, duplicated or renamed (tensors: also NaN, wrong
    shapes and dtypes, meta tensors)."""
    doc = copy.deepcopy(doc)
    paths = list(_nodes(doc))
    if not paths:
        return rng.choice(SPECIAL), "the whole document replaced"
    shallow = [p for p in paths if len(p) <= 2]  # named fields (iteration, fl_x, ...) more often than array cells
    path = rng.choice(shallow if shallow and rng.random() < 0.5 else paths)
    parent, key = _parent(doc, path), path[-1]
    value = parent[key]
    where = "/".join(map(str, path))
    if tensors and isinstance(value, torch.Tensor) and rng.random() < 0.7:
        new, what = _mutate_tensor(rng, value)
        _set(doc, path, new)
        return doc, f"{where}: {what}"
    op = rng.choice(["special", "special", "special", "delete", "nest", "duplicate", "rename"])
    if op == "delete" and not isinstance(parent, tuple):
        del parent[key]
        return doc, f"{where} deleted"
    if op == "nest":
        depth = rng.choice([5, 50, 200 if tensors else 900])  # torch.save itself recurses on deeper nesting
        for _ in range(depth):
            value = [value]
        _set(doc, path, value)
        return doc, f"{where} nested {depth} lists deep"
    if op == "duplicate" and isinstance(parent, list):
        parent.insert(key, copy.deepcopy(value))
        return doc, f"{where} duplicated"
    if op == "rename" and isinstance(parent, dict):
        parent[f"{key}_x" if isinstance(key, str) else str(key)] = parent.pop(key)
        return doc, f"{where} renamed"
    new = rng.choice(SPECIAL)
    if not tensors and rng.random() < 0.05:
        new = BOMB
    _set(doc, path, new)
    return doc, f"{where} = {str(new)[:40]!r}"


def _mutate_tensor(rng: random.Random, t: torch.Tensor) -> tuple[torch.Tensor, str]:
    kind = rng.choice(["nan", "inf", "huge", "shape", "dtype", "empty", "meta", "scalar", "transpose"])
    if kind in ("nan", "inf", "huge") and t.numel():
        t = t.clone()
        if not t.is_floating_point():
            t = t.float()
        flat = t.view(-1)
        flat[rng.randrange(flat.numel())] = {"nan": float("nan"), "inf": float("-inf"), "huge": 3e38}[kind]
        return t, f"one value set to {kind}"
    if kind == "shape":
        if t.dim() == 0:
            return t.reshape(1, 1), "scalar made [1,1]"
        if rng.random() < 0.5:
            return torch.cat([t, t[:1]]), f"{list(t.shape)} given an extra row"
        return t.reshape(t.shape[0], -1)[:, :-1] if t.numel() else t.reshape(-1), f"{list(t.shape)} lost a column"
    if kind == "dtype":
        dtype = rng.choice([torch.int32, torch.int64, torch.float64, torch.float16, torch.bfloat16, torch.bool,
                            torch.uint8, torch.complex64])
        return t.to(dtype), f"{t.dtype} made {dtype}"
    if kind == "empty":
        return t[:0] if t.dim() else torch.empty(0), "emptied"
    if kind == "meta":
        return torch.empty(t.shape, dtype=t.dtype, device="meta"), "made a meta tensor (no data)"
    if kind == "scalar":
        return torch.tensor(1.5), "replaced by a scalar"
    return (t.t() if t.dim() == 2 else t.flip(0)) if t.dim() else t, "transposed or flipped"


def dump_json(doc) -> str:
    text = json.dumps(doc, allow_nan=True)
    return text.replace(json.dumps(BOMB), "[" * 100_000 + "]" * 100_000)


def mutate_json_file(rng: random.Random, path: Path) -> str:
    """Mutate a JSON file in place: a tree mutation, or (a quarter of the time) its text as bytes."""
    text = path.read_bytes()
    if rng.random() < 0.25:
        data, what = mutate_bytes(rng, text)
        path.write_bytes(data)
        return f"{path.name}: {what}"
    doc, what = mutate_tree(rng, json.loads(text))
    path.write_text(dump_json(doc))
    return f"{path.name}: {what}"


NUMBER = re.compile(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?")
TOKENS = [b"nan", b"inf", b"-inf", b"1e308", b"-1", b"0", b"99999999999999999999999", b"1e-300", b"x", b"",
          b"4294967297", b"-2147483649", b"0.5"]


def mutate_text(rng: random.Random, data: bytes, *, hot: int | None = None) -> tuple[bytes, str]:
    """Text formats (COLMAP .txt, ASCII PLY): a number token replaced, a line deleted or duplicated, or bytes."""
    lines = data.split(b"\n")
    kind = rng.choice(["token", "token", "token", "line", "bytes"])
    numbered = [(i, m) for i, line in enumerate(lines) if not line.startswith(b"#")
                for m in NUMBER.finditer(line)]
    if kind == "token" and numbered:
        i, m = rng.choice(numbered)
        new = rng.choice(TOKENS)
        lines[i] = lines[i][:m.start()] + new + lines[i][m.end():]
        return b"\n".join(lines), f"line {i + 1}: {m.group().decode()!r} -> {new.decode()!r}"
    if kind == "line" and len(lines) > 1:
        i = rng.randrange(len(lines))
        if rng.random() < 0.5:
            del lines[i]
            return b"\n".join(lines), f"line {i + 1} deleted"
        lines.insert(i, lines[i])
        return b"\n".join(lines), f"line {i + 1} duplicated"
    return mutate_bytes(rng, data, hot)


PLY_TYPES = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "float64", "list",
             "half", ""]


def mutate_ply(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """PLY: element counts (bigger, smaller, huge), property types, dropped or duplicated properties, a NaN or
    infinity in the body, or bytes anywhere (often in the header)."""
    end = data.find(b"end_header\n") + len(b"end_header\n")
    header, body = data[:end].decode("ascii").split("\n"), data[end:]
    kind = rng.choice(["count", "type", "drop", "dup", "poke", "bytes", "bytes"])
    elements = [i for i, line in enumerate(header) if line.startswith("element ")]
    props = [i for i, line in enumerate(header) if line.startswith("property ")]
    if kind == "count" and elements:
        i = rng.choice(elements)
        _, name, count = header[i].split()
        new = rng.choice([int(count) + 1, max(int(count) - 1, 0), 0, int(count) * 2, 2**31, 2**32 + 1, 2**64 + 3,
                          10**18, int(count) // 2])
        header[i] = f"element {name} {new}"
        what = f"element {name} {count} -> {new}"
    elif kind == "type" and props:
        i = rng.choice(props)
        parts = header[i].split()
        new = rng.choice(PLY_TYPES)
        header[i] = " ".join(["property", new, parts[-1]])
        what = f"{header[i]!r} (was {parts[1]})"
    elif kind == "drop" and props:
        i = rng.choice(props)
        what = f"{header.pop(i)!r} dropped"
    elif kind == "dup" and props:
        i = rng.choice(props)
        header.insert(i, header[i])
        what = f"{header[i]!r} duplicated"
    elif kind == "poke" and len(body) >= 4 and b"binary" in data[:end]:
        i = rng.randrange(len(body) // 4) * 4
        value = rng.choice([float("nan"), float("inf"), float("-inf"), 3e38, -3e38, 1e-45])
        body = body[:i] + struct.pack("<f", value) + body[i + 4:]
        what = f"float at body offset {i} = {value}"
    else:
        return mutate_text(rng, data, hot=end) if b"format ascii" in data[:end] else mutate_bytes(rng, data, hot=end)
    return "\n".join(header).encode("ascii") + body, what


# --- seeds -------------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Seeds:
    root: Path
    data: Path            # a synthetic COLMAP dataset the runs were trained on
    run: Path             # an interrupted run (config.json, checkpoint.pt)
    finished: Path        # a finished run (and model.pt)
    model_pt: list       # gabor; gabor with pruned waves (its packed layout); 2dgs with SH
    ply_binary: Path
    ply_ascii: Path
    colmap_bin: Path
    colmap_txt: Path
    blender: Path         # transforms_train.json / transforms_test.json, camera_angle_x
    nerfstudio: Path      # transforms.json with fl_x, cx, w, h and a ply_file_path point cloud (uchar colours)


def _ascii_copy(src: Path, dst: Path) -> Path:
    """The binary little-endian float PLY `src` as an ASCII PLY."""
    data = src.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().replace("format binary_little_endian 1.0", "format ascii 1.0")
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    values = np.frombuffer(data[end:], dtype="<f4").reshape(-1, len(props))
    rows = "\n".join(" ".join(repr(float(v)) for v in row) for row in values)
    dst.write_text(header + rows + "\n")
    return dst


def _points_ply(path: Path, n: int = 16) -> Path:
    g = np.random.default_rng(0)
    arr = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                             ("blue", "u1")])
    for k in "xyz":
        arr[k] = g.uniform(-0.5, 0.5, n)
    for k in ("red", "green", "blue"):
        arr[k] = g.integers(0, 256, n)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.write_bytes(header.encode() + arr.tobytes())
    return path


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> Seeds:
    from test_data_inputs import _blender, _colmap_dataset

    from splatzoo.data.colmap import write_model
    from splatzoo.data.synthetic import make_synthetic_scene, synthetic_cameras
    from splatzoo.export import save_ply
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig
    from splatzoo.zoo import create_model, save_model

    root = tmp_path_factory.mktemp("fuzz-seeds")
    g = torch.Generator().manual_seed(0)
    model = create_model("gabor", torch.randn(12, 3, generator=g), torch.rand(12, 3, generator=g), n_waves=2)
    save_model(model, root / "model.pt")
    save_ply(model, root / "model.ply")
    pruned = create_model("gabor", torch.randn(12, 3, generator=g), torch.rand(12, 3, generator=g), n_waves=3,
                          prune_waves=0.02)
    with torch.no_grad():
        pruned.wave_weights.mul_(torch.rand(pruned.wave_weights.shape, generator=g) * 3)
    assert pruned.prune_waves(0.003)["removed"] > 0
    save_model(pruned, root / "pruned.pt")
    save_model(create_model("2dgs", torch.randn(5, 3, generator=g), torch.rand(5, 3, generator=g), sh_degree=1),
               root / "sh.pt")
    plain = create_model("2dgs", torch.randn(6, 3, generator=g), torch.rand(6, 3, generator=g))
    ply = save_ply(plain, root / "2dgs.ply")
    _ascii_copy(ply, root / "2dgs-ascii.ply")

    data = make_synthetic_scene("plain", root / "data", views=4, width=24, height=24)
    cfg = TrainConfig(iterations=3, backend="reference", num_primitives=20, seed=1)
    train(data, "gabor", {"n_waves": 2}, cfg, root / "run", progress=False, evaluate_at_end=False, stop_after=2)
    shutil.copytree(root / "run", root / "finished")
    train(None, resume=True, out=root / "finished", progress=False, evaluate_at_end=False)

    colmap_bin, _ = _colmap_dataset(root / "colmap-bin", n=3, w=32, h=24)
    colmap_txt, cams = _colmap_dataset(root / "colmap-txt", n=3, w=32, h=24)
    shutil.rmtree(colmap_txt / "sparse" / "0")
    names = sorted(p.name for p in (colmap_txt / "images").iterdir())
    g2 = np.random.default_rng(1)
    write_model(colmap_txt / "sparse" / "0", cams, names, g2.uniform(-1, 1, (6, 3)), g2.uniform(0, 1, (6, 3)),
                text=True)
    blender = _blender(root / "blender", n=3)
    shutil.copytree(blender / "train", blender / "test")
    (blender / "transforms_test.json").write_text((blender / "transforms_train.json").read_text().replace("/train/",
                                                                                                         "/test/"))

    ns = root / "nerfstudio"
    (ns / "images").mkdir(parents=True)
    frames = []
    import cv2

    for i, cam in enumerate(synthetic_cameras("plain", 3, 20, 16)):
        cv2.imwrite(str(ns / "images" / f"frame_{i:05d}.png"), (np.random.default_rng(i).random((16, 20, 3)) * 255)
                    .astype(np.uint8))
        c2w = torch.linalg.inv(cam.world_to_camera).numpy() @ np.diag([1.0, -1, -1, 1])
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": c2w.tolist()})
    (ns / "transforms.json").write_text(json.dumps({
        "fl_x": 20.0, "fl_y": 20.0, "cx": 10.0, "cy": 8.0, "w": 20, "h": 16, "camera_model": "OPENCV",
        "ply_file_path": "sparse_pc.ply", "frames": frames}))
    _points_ply(ns / "sparse_pc.ply")
    return Seeds(root, Path(data), root / "run", root / "finished",
                 [root / "model.pt", root / "pruned.pt", root / "sh.pt"], root / "model.ply",
                 root / "2dgs-ascii.ply", colmap_bin, colmap_txt, blender, ns)


# --- what a valid result is ---------------------------------------------------------------------------------------

def valid_model(model) -> None:
    from splatzoo.types import Camera

    for name, t in {**dict(model.named_parameters()), **dict(model.named_buffers())}.items():
        if t.is_floating_point():
            assert bool(torch.isfinite(t).all()), f"loaded model has non-finite {name}"
    rows = {k: v.shape[0] for k, v in model.per_primitive().items()}
    assert len(set(rows.values())) <= 1, f"per-primitive parameters disagree: {rows}"
    cam = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=12, height=10, dtype=torch.float32)
    with torch.no_grad():
        out = model.render(cam, backend="reference")
    assert bool(torch.isfinite(out.rgb).all()), "the loaded model renders non-finite colours"


def valid_scene(scene) -> None:
    from splatzoo.data.scene import check_cameras

    assert scene.train, "a scene without training views"
    check_cameras(scene.views, scene.root)
    assert scene.points.shape[0] == scene.colors.shape[0] and scene.points.shape[1:] == (3,)
    assert bool(torch.isfinite(scene.points).all()), "initial points hold NaN or infinity"
    c = scene.colors
    assert bool(torch.isfinite(c).all()) and (c.numel() == 0 or (float(c.min()) >= 0 and float(c.max()) <= 1)), \
        "initial colours outside [0, 1]"
    assert math.isfinite(scene.extent) and scene.extent > 0
    for v in scene.views:
        img = v.image_float()
        assert tuple(img.shape) == (v.camera.height, v.camera.width, 3)


def load_and_decode(path, **options):
    """load_scene and every view's pixels: what training reads."""
    from splatzoo.data import load_scene

    def load():
        scene = load_scene(path, **options)
        for v in scene.views:
            v.image()
        return scene
    return load


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


# --- the targets ------------------------------------------------------------------------------------------------

def fuzz_ply_binary(case, rng, seeds, tmp):
    from splatzoo.export import load_ply

    path = tmp / "m.ply"
    data, what = mutate_ply(rng, seeds.ply_binary.read_bytes())
    path.write_bytes(data)
    outcome(case, what, lambda: load_ply(path), valid_model)


def fuzz_ply_ascii(case, rng, seeds, tmp):
    from splatzoo.export import load_ply

    path = tmp / "m.ply"
    data, what = mutate_ply(rng, seeds.ply_ascii.read_bytes())
    path.write_bytes(data)
    outcome(case, what, lambda: load_ply(path), valid_model)


def fuzz_model_pt(case, rng, seeds, tmp):
    from splatzoo.zoo import load_model

    path, seed = tmp / "model.pt", rng.choice(seeds.model_pt)
    if rng.random() < 0.3:
        data, what = mutate_bytes(rng, seed.read_bytes(), hot=512)
        path.write_bytes(data)
    else:
        ckpt, what = mutate_tree(rng, torch.load(seed, weights_only=True), tensors=True)
        torch.save(ckpt, path)
    outcome(case, f"{seed.name}: {what}", lambda: load_model(path), valid_model)


def _resume(run: Path, **kw):
    from splatzoo.runs import train

    return lambda: train(None, resume=True, out=run, progress=False, evaluate_at_end=False, **kw)


def fuzz_checkpoint(case, rng, seeds, tmp):
    from splatzoo.zoo import load_model

    run = _copy(seeds.run, tmp / "run")
    if rng.random() < 0.15:
        data, what = mutate_bytes(rng, (run / "checkpoint.pt").read_bytes(), hot=512)
        (run / "checkpoint.pt").write_bytes(data)
    else:
        state, what = mutate_tree(rng, torch.load(run / "checkpoint.pt", weights_only=True), tensors=True)
        torch.save(state, run / "checkpoint.pt")

    def valid(result):
        valid_model(result.model)
        valid_model(load_model(run / "model.pt"))
    outcome(case, what, _resume(run), valid)


def fuzz_run_config(case, rng, seeds, tmp):
    from splatzoo.runs import Run

    run, finished = _copy(seeds.run, tmp / "run"), _copy(seeds.finished, tmp / "finished")
    what = mutate_json_file(rng, run / "config.json")
    shutil.copy(run / "config.json", finished / "config.json")
    outcome(case, what, _resume(run, stop_after=0))

    def load():
        model, scene, record = Run(finished).load()
        Run(finished).train_config(record)
        return model, scene

    outcome(case, what, load, lambda r: (valid_model(r[0]), valid_scene(r[1])))


def fuzz_colmap_bin(case, rng, seeds, tmp):
    root = _copy(seeds.colmap_bin, tmp / "d")
    sparse = root / "sparse" / "0"
    victim = rng.choice(sorted(sparse.glob("*.bin")))
    data, what = mutate_bytes(rng, victim.read_bytes(), hot=64)
    victim.write_bytes(data)
    outcome(case, f"{victim.name}: {what}", load_and_decode(root), valid_scene)


def fuzz_colmap_txt(case, rng, seeds, tmp):
    root = _copy(seeds.colmap_txt, tmp / "d")
    victim = rng.choice(sorted((root / "sparse" / "0").glob("*.txt")))
    data, what = mutate_text(rng, victim.read_bytes())
    victim.write_bytes(data)
    outcome(case, f"{victim.name}: {what}", load_and_decode(root), valid_scene)


def fuzz_blender_json(case, rng, seeds, tmp):
    src = rng.choice([seeds.blender, seeds.nerfstudio])
    root = _copy(src, tmp / "d")
    victim = rng.choice(sorted(root.glob("transforms*.json")))
    what = mutate_json_file(rng, victim)
    outcome(case, what, load_and_decode(root), valid_scene)


def fuzz_images(case, rng, seeds, tmp):
    src = rng.choice([seeds.blender, seeds.nerfstudio, seeds.colmap_bin])
    root = _copy(src, tmp / "d")
    victim = rng.choice(sorted(p for p in root.rglob("*.png")))
    data, what = mutate_bytes(rng, victim.read_bytes(), hot=64)
    victim.write_bytes(data)
    outcome(case, f"{victim.relative_to(root)}: {what}", load_and_decode(root), valid_scene)


def fuzz_points_ply(case, rng, seeds, tmp):
    root = _copy(seeds.nerfstudio, tmp / "d")
    victim = root / "sparse_pc.ply"
    if rng.random() < 0.2:  # the same cloud as ASCII
        arr = np.frombuffer(victim.read_bytes().split(b"end_header\n", 1)[1],
                            dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
        header = victim.read_text(errors="replace").split("end_header\n")[0].replace("binary_little_endian", "ascii")
        rows = "\n".join(" ".join(str(v) for v in row) for row in arr.tolist())
        victim.write_text(header + "end_header\n" + rows + "\n")
    data, what = mutate_ply(rng, victim.read_bytes())
    victim.write_bytes(data)
    outcome(case, f"sparse_pc.ply: {what}", load_and_decode(root), valid_scene)


# The command line: options mutated one or two at a time. Every command is pointed at something that makes it fail
# fast or finish at once (a missing dataset or run, or a copy of a tiny finished run for the cheap commands), so no
# case starts real work.
NUMBERS = ["-1", "0", "1", "2", "-5", "1e308", "1e400", "9223372036854775808", "99999999999999999999999", "nan",
           "NaN", "inf", "-inf", "abc", "", "2.5", "0x10", " 3", "1_000", "a" * 5000, "\u2603", "-", "--"]
MODELS = ["gabr", "gabor:n_waves=x", "gabor:n_waves=1e9", "gabor:n_waves=-1", ":", "gabor:", "2dgs:sh_degree=9",
          "gabor:n_waves=nan", "gabor:foo=1", "gabor:n_waves", "2dgs", "gabor,2dgs", "", "a" * 3000]
BACKENDS = ["cudaa", "", "CPU", "reference", "none", "a" * 3000]
BACKGROUNDS = ["white", "1,2", "nan,0,0", "0.5,0.5,0.5", "random", "purple", "1,1,1,1", "inf,0,0", "-1,0,0", "2,2,2"]

CLI = {
    "train": {"--model": MODELS, "--iterations": NUMBERS, "--backend": BACKENDS, "--resolution": NUMBERS,
              "--max-width": NUMBERS, "--test-every": NUMBERS, "--background": BACKGROUNDS,
              "--strategy": ["mcmc", "adc", "x", ""], "--num-primitives": NUMBERS, "--max-primitives": NUMBERS,
              "--seed": NUMBERS, "--lambda-dist": NUMBERS, "--lambda-normal": NUMBERS,
              "--checkpoint-every": NUMBERS, "--checkpoint-minutes": NUMBERS, "--batch-size": NUMBERS,
              "--nproc": NUMBERS, "--random-downscale": NUMBERS, "--n-waves": NUMBERS, "--prune-waves": NUMBERS,
              "--sh-degree": NUMBERS, "--no-such-option": NUMBERS, "--resume": None, "--overwrite": None},
    "eval": {"--backend": BACKENDS, "--lpips-net": ["vgg", "alex", "x", ""], "--lpips-convention": ["3dgs", "x"],
             "--scale": ["0.5", "0.5,0.25", "2", "0", "-1", "nan", "x", ",", "1e-300", "0.5,,0.5"]},
    "render": {"--split": ["test", "train", "x", ""], "--frames": NUMBERS, "--backend": BACKENDS, "--video": None},
    "extract-mesh": {"--voxel-size": NUMBERS, "--sdf-trunc": NUMBERS, "--depth-trunc": NUMBERS,
                     "--depth": ["median", "expected", "x"], "--alpha-threshold": NUMBERS, "--backend": BACKENDS,
                     "--keep-largest": None},
    "export": {},
    "compare": {"MODELS": MODELS, "--iterations": NUMBERS, "--num-primitives": NUMBERS, "--scene": ["sweater", "x"],
                "--backend": BACKENDS, "--resolution": NUMBERS, "--max-width": NUMBERS, "--test-every": NUMBERS,
                "--background": BACKGROUNDS, "--random-downscale": NUMBERS, "--seed": NUMBERS, "--quick": None,
                "--equal-bytes": None},
    "view": {"--port": NUMBERS, "--host": ["127.0.0.1", "", "x" * 300, "::1", "999.1.1.1"], "--backend": BACKENDS},
}
# commands that are cheap on a real (tiny, finished) run when these options are left alone
CHEAP_ON_A_RUN = {"render": {"--frames", "--video", "--backend"}, "export": set()}


def fuzz_cli(case, rng, seeds, tmp, monkeypatch):
    from splatzoo.cli import app

    monkeypatch.chdir(tmp)  # a default output folder (runs/...) lands here
    import splatzoo.viewer

    # a viewer that starts (a valid model, a free port) serves until stopped: here it stops at once
    monkeypatch.setattr(splatzoo.viewer.Viewer, "serve_forever", lambda self: self.stop())
    command = rng.choice(sorted(CLI))
    options = CLI[command]
    chosen = rng.sample(sorted(options), k=min(len(options), rng.choice([1, 1, 2])))
    absent = tmp / "absent"
    target = rng.choice([absent, absent, seeds.model_pt[0], tmp / ("x" * 300)])
    real_run = command in CHEAP_ON_A_RUN and not set(chosen) & CHEAP_ON_A_RUN[command] and rng.random() < 0.7
    if real_run:
        target = _copy(seeds.finished, tmp / "run")
    args = [command]
    if command == "compare":
        args += ["gabor"] if "MODELS" not in chosen else [rng.choice(MODELS)]
        args += ["--data", str(target), "--out", str(tmp / "cmp")]
    elif command == "train":
        args += [str(target), "--out", str(tmp / "out")]
    else:
        args += [str(target)]
    if command == "export":
        args += ["--out", rng.choice([str(tmp / "m.ply"), str(tmp / "m.txt"), str(tmp), str(tmp / "no" / "m.ply"),
                                      str(tmp / ("y" * 300 + ".ply")), "", str(target / "model.pt")])]
    if command in ("render", "eval", "extract-mesh") and real_run:
        args += ["--out", str(tmp / "renders")]
    if real_run and "--backend" in CLI[command]:
        args += ["--backend", "reference"]
    for option in chosen:
        if option == "MODELS":
            continue
        values = options[option]
        args += [option] if values is None else [option, rng.choice(values)]
    what = " ".join(a if len(a) < 60 else a[:20] + "..." for a in args)
    runner = CliRunner()
    before = folder_digest(target) if real_run else None

    def run():
        return runner.invoke(app, args)

    result = outcome(case, what, run)
    if real_run and result.exit_code != 0:
        assert folder_digest(target) == before, f"{case} ({what}): refused, but the run folder changed"
    if result.exception is None or isinstance(result.exception, SystemExit):
        assert result.exit_code in (0, 2), f"{case} ({what}): exit code {result.exit_code}\n{result.output}"
        assert "Traceback" not in result.output, f"{case} ({what}):\n{result.output}"
    elif not isinstance(result.exception, SplatzooError):  # main() prints `error: ...` and exits 2 for these
        pytest.fail(f"{case} ({what}): {type(result.exception).__name__}, not a SplatzooError\n"
                    + "".join(traceback.format_exception(*result.exc_info)), pytrace=False)


# --- the newer doors: third-party PLYs, splat formats, lens distortion, --init-from, option strings ---------------

def gaussian_ply(path: Path, n: int = 8, *, layout: str = "3dgs", dtype: str = "<f4", rest: int = 0,
                 normals: bool = True, seed: int = 0) -> Path:
    """A splat PLY as other tools write it: 3DGS (scale_0..2) or 2DGS (scale_0..1) columns, SH rest coefficients or
    not, normals or not, float or double, little- or big-endian."""
    g = np.random.default_rng(seed)
    names = (["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + [f"f_dc_{i}" for i in range(3)]
             + [f"f_rest_{i}" for i in range(rest)] + ["opacity"]
             + [f"scale_{i}" for i in range(3 if layout == "3dgs" else 2)] + [f"rot_{i}" for i in range(4)])
    arr = np.zeros(n, dtype=[(k, dtype) for k in names])
    for k in "xyz":
        arr[k] = g.uniform(-0.5, 0.5, n)
    for k in names:
        if k.startswith("f_dc"):
            arr[k] = g.normal(0, 0.5, n)
        elif k.startswith("f_rest"):
            arr[k] = g.normal(0, 0.05, n)
        elif k.startswith("scale"):
            arr[k] = g.uniform(-4, -2, n)
    arr["opacity"] = g.normal(1, 0.5, n)
    q = g.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for i in range(4):
        arr[f"rot_{i}"] = q[:, i]
    order = "binary_little_endian" if dtype[0] == "<" else "binary_big_endian"
    kind = {"f4": "float", "f8": "double"}[dtype[1:]]
    header = (f"ply\nformat {order} 1.0\nelement vertex {n}\n" + "".join(f"property {kind} {k}\n" for k in names)
              + "end_header\n")
    path.write_bytes(header.encode() + arr.tobytes())
    return path


PLY_VARIANTS = {"3dgs-sh0": {}, "3dgs-sh3": {"rest": 45}, "2dgs": {"layout": "2dgs"},
                "no-normals": {"normals": False}, "double": {"dtype": "<f8"}, "big-endian": {"dtype": ">f4"}}


@pytest.fixture(scope="module")
def ply_variants(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ply-variants")
    return {name: gaussian_ply(root / f"{name}.ply", **kw) for name, kw in PLY_VARIANTS.items()}


def fuzz_ply_variants(case, rng, seeds, tmp, variants):
    from splatzoo.export import load_source

    name = rng.choice(sorted(variants))
    path = tmp / "splats.ply"
    data, what = mutate_ply(rng, variants[name].read_bytes())
    path.write_bytes(data)
    outcome(case, f"{name}: {what}", lambda: load_source(path)[0], valid_model)


SPLAT_SUFFIXES = (".spz", ".splat", ".ksplat", ".sog")


@pytest.fixture(scope="module")
def splat_files(seeds) -> dict[str, Path]:
    """The 2dgs seed converted by splat-transform to each format it reads (skipped where it is not installed)."""
    from splatzoo.splat_tools import convert_file, find_splat_transform

    try:
        find_splat_transform()
    except SplatzooError as e:
        pytest.skip(f"splat-transform is not installed: {e}")
    files = {suffix: convert_file(seeds.root / "2dgs.ply", seeds.root / f"2dgs{suffix}")
             for suffix in SPLAT_SUFFIXES if suffix != ".ksplat"}  # splat-transform reads .ksplat, never writes it
    from test_hostile_models import _ksplat

    files[".ksplat"] = seeds.root / "splats.ksplat"
    files[".ksplat"].write_bytes(_ksplat(6))
    return files


def _mutate_spz(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """SPZ: a header (magic, version, count, SH degree, fractional bits, flags) and columns, gzip-compressed (up to
    version 3) or not (version 4, its columns compressed one by one): the header's fields inside the stream, or the
    bytes of the stream or the file."""
    import gzip

    zipped = data[:2] == b"\x1f\x8b"
    if rng.random() < 0.3:
        return mutate_bytes(rng, data, hot=32)
    raw = bytearray(gzip.decompress(data) if zipped else data)
    if rng.random() < 0.6:
        field, offset, fmt = rng.choice([("version", 4, "<I"), ("count", 8, "<I"), ("SH degree", 12, "B"),
                                         ("fractional bits", 13, "B"), ("flags", 14, "B")])
        value = rng.choice([0, 1, 2, 3, 4, 5, 7, 12, 24, 31, 32, 255] + ([2**31, 2**32 - 1] if fmt == "<I" else []))
        struct.pack_into(fmt, raw, offset, value)
        what = f"spz {field} = {value}"
    else:
        body, what = mutate_bytes(rng, bytes(raw), hot=32)
        raw = bytearray(body)
        what = f"inside the gzip stream: {what}" if zipped else what
    return (gzip.compress(bytes(raw)) if zipped else bytes(raw)), what


def _mutate_sog(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """SOG: a zip of meta.json and WebP images; meta.json's tree, one image's bytes, or the zip's bytes."""
    import io
    import zipfile

    if rng.random() < 0.25:
        return mutate_bytes(rng, data, hot=64)
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        members = {n: z.read(n) for n in z.namelist()}
    victim = "meta.json" if "meta.json" in members and rng.random() < 0.6 else rng.choice(sorted(members))
    if victim.endswith(".json"):
        doc, what = mutate_tree(rng, json.loads(members[victim]))
        members[victim] = dump_json(doc).encode()
    else:
        members[victim], what = mutate_bytes(rng, members[victim], hot=64)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        for n, b in members.items():
            z.writestr(n, b)
    return out.getvalue(), f"{victim}: {what}"


def _distinct_positions(model) -> None:
    """A file of distinct splats read back as one point (a scale or offset gone wrong) is a silent wrong result."""
    valid_model(model)
    means = model.per_primitive().get("means")
    if means is not None and means.shape[0] > 1:
        assert torch.unique(means, dim=0).shape[0] > 1, "every splat was read at one point"


def fuzz_splat_formats(case, rng, seeds, tmp, files):
    from splatzoo.export import load_source

    suffix = rng.choice(SPLAT_SUFFIXES)
    data = files[suffix].read_bytes()
    if suffix == ".spz":
        data, what = _mutate_spz(rng, data)
    elif suffix == ".sog":
        data, what = _mutate_sog(rng, data)
    elif rng.random() < 0.5:  # .splat / .ksplat: a float somewhere made NaN, huge or tiny
        i = rng.randrange(max(1, len(data) // 4)) * 4
        value = rng.choice([float("nan"), float("inf"), 3e38, -3e38, 1e-45, 0.0])
        data, what = data[:i] + struct.pack("<f", value) + data[i + 4:], f"float at offset {i} = {value}"
    else:
        data, what = mutate_bytes(rng, data, hot=64)
    path = tmp / f"splats{suffix}"
    path.write_bytes(data)
    outcome(case, f"{suffix}: {what}", lambda: load_source(path)[0], _distinct_positions)


DISTORTION = [0.0, 1e-3, -0.05, 0.2, -0.6, 1.5, 1e3, -1e3, 1e6, -1e6, 1e308, float("nan"), float("inf"), "x", None,
              [], True]
CAMERA_MODELS = ["OPENCV", "OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_RADIAL", "FISHEYE", "EQUIRECTANGULAR",
                 "x", 7]


def fuzz_distortion(case, rng, seeds, tmp):
    """transforms.json's lens: its camera model, fisheye flag and distortion coefficients, for all frames or one."""
    root = _copy(seeds.nerfstudio, tmp / "d")
    doc = json.loads((root / "transforms.json").read_text())
    width, height = doc["w"], doc["h"]
    changes = []
    if rng.random() < 0.5:
        doc["camera_model"] = rng.choice(CAMERA_MODELS)
        changes.append(f"camera_model={doc['camera_model']!r}")
    if rng.random() < 0.2:
        doc["is_fisheye"] = rng.choice([True, False, "x", 1])
        changes.append(f"is_fisheye={doc['is_fisheye']!r}")
    for key in rng.sample(["k1", "k2", "k3", "k4", "p1", "p2"], rng.randint(1, 3)):
        where = doc if rng.random() < 0.7 else rng.choice(doc["frames"])
        where[key] = rng.choice(DISTORTION)
        changes.append(f"{'' if where is doc else 'a frame: '}{key}={where[key]!r}")
    (root / "transforms.json").write_text(json.dumps(doc, allow_nan=True))

    def valid(scene):
        valid_scene(scene)
        for v in scene.views:  # undistortion crops; a crop to a sliver of the photo is not a scene to train on
            assert v.camera.width >= width / 4 and v.camera.height >= height / 4, \
                f"{v.name} undistorted to {v.camera.width}x{v.camera.height} of a {width}x{height} photo"
    outcome(case, "; ".join(changes), load_and_decode(root), valid)


def fuzz_init_from(case, rng, seeds, tmp, variants):
    """`train --init-from FILE` with a damaged model file: refused before a run folder is made, or a run that
    trains to a finite model."""
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    source = rng.choice([seeds.ply_binary, seeds.ply_ascii, *seeds.model_pt, *variants.values()])
    path = tmp / f"init{source.suffix}"
    if source.suffix == ".ply":
        data, what = mutate_ply(rng, source.read_bytes())
        path.write_bytes(data)
    else:
        ckpt, what = mutate_tree(rng, torch.load(source, weights_only=True), tensors=True)
        torch.save(ckpt, path)
    out = tmp / "run"
    cfg = TrainConfig(iterations=2, backend="reference", seed=1, log_every=1)
    result = outcome(case, f"{source.name}: {what}",
                     lambda: train(seeds.data, None, None, cfg, out, init_from=path, progress=False,
                                   evaluate_at_end=False),
                     lambda r: valid_model(r.model))
    if result is None:
        assert not out.exists(), f"{case} ({source.name}: {what}): a refused --init-from left {out}"


def _option_value(rng: random.Random) -> str:
    return rng.choice(NUMBERS[:-3] + ["true", "false", "yes", "3dgs", "exact", "median", "x,y", "=", ":", "1=2"])


def fuzz_option_strings(case, rng, seeds, tmp):
    """'model:key=value,...' and 'format:key=value,...' as a user types them: names, keys and values of every
    member and exporter, repeated or misspelt keys, missing '=' and stray separators."""
    from splatzoo.export import list_formats, parse_format
    from splatzoo.options import model_spec
    from splatzoo.zoo import get_model_spec, list_models, make_config

    models = rng.random() < 0.5
    name = rng.choice((list_models() if models else list_formats()) + ["x", ""])
    try:
        cls = get_model_spec(name).config_cls if models else parse_format(name)[1].__class__
        keys = [f.name for f in dataclasses.fields(cls)]
    except (SplatzooError, TypeError):
        keys = []
    keys += ["x", "", " ", "n-waves", "--seed"]
    items = [f"{rng.choice(keys)}={_option_value(rng)}" for _ in range(rng.randint(0, 4))]
    if items and rng.random() < 0.2:
        items.append(items[0].split("=")[0] + "=" + _option_value(rng))  # a key given twice
    if rng.random() < 0.1:
        items.append(rng.choice(keys))  # no '='
    text = name + rng.choice([":", ":", "::", ": "]) + rng.choice([",", ",", ", ", ",,"]).join(items)

    def valid(options) -> None:
        if dataclasses.is_dataclass(options):
            for field in dataclasses.fields(options):
                value = getattr(options, field.name)
                if isinstance(value, float):
                    assert math.isfinite(value), f"{field.name} = {value}"
    if models:
        outcome(case, text, lambda: make_config(*model_spec(text)[:1], **model_spec(text)[1]), valid)
    else:
        outcome(case, text, lambda: parse_format(text)[1], valid)


BENCH = {"--json": ["out.json", "", "/proc/x.json", ".", "missing/x.json", "a" * 300 + ".json", "/dev/null"],
         "--repeats": NUMBERS, "--backends": ["cpu", "reference", "cuda", "bogus", "", ",", "cpu,cpu", "a" * 3000],
         "--waves": ["0", "4", "4a", "0t4", "0b", "x", "-1", "1000000000", "0,0", "", "0t0", "0t1000", "4ab", ","],
         "--quick": None, "--gpu": None, "--fps": ["absent", "model.pt", "run", "/dev/zero", "."],
         "--backend": BACKENDS, "--training": None, "--data": ["absent", "data", "model.pt"],
         "--size": ["16x16", "100000x100000", "0x0", "x", "8x", "1e3x8", "-8x8", "8x8x8", ""],
         "--views": NUMBERS, "--iterations": NUMBERS, "--models": ["2dgs", "gabor", "x", "", "2dgs,2dgs",
                                                                    "gabor:n_waves=2", ","],
         "--gsplat-examples": ["absent", "."]}


def fuzz_bench(case, rng, seeds, tmp, monkeypatch):
    """`splatzoo bench` with its options mutated: everything asked for is checked before anything runs (the
    benchmarks themselves are replaced by recorders here), so a case is a named refusal or a checked request."""
    import splatzoo.cli as cli
    import splatzoo.evaluate as evaluate

    calls = []
    real = cli._bench_module

    def recorded(name):
        module = real(name)
        module.run_benchmark = lambda **kw: calls.append(kw)
        module.run = lambda argv, **kw: calls.append({"argv": argv})
        return module
    monkeypatch.setattr(cli, "_bench_module", recorded)
    monkeypatch.setattr(evaluate, "fps_report", lambda *a, **k: calls.append({"fps": True}) or [])
    monkeypatch.chdir(tmp)
    shutil.copy(seeds.model_pt[0], tmp / "model.pt")
    _copy(seeds.finished, tmp / "run")
    _copy(seeds.data, tmp / "data")
    args = ["bench", "--json", "out.json"]
    for option in rng.sample(sorted(BENCH), k=rng.choice([1, 2, 2, 3])):
        values = BENCH[option]
        args += [option] if values is None else [option, rng.choice(values)]
    what = " ".join(a if len(a) < 60 else a[:20] + "..." for a in args)
    result = outcome(case, what, lambda: CliRunner().invoke(cli.app, args))
    if result.exception is not None and not isinstance(result.exception, (SystemExit, SplatzooError)):
        pytest.fail(f"{case} ({what}): {type(result.exception).__name__}, not a SplatzooError\n"
                    + "".join(traceback.format_exception(*result.exc_info)), pytrace=False)
    assert "Traceback" not in result.output, f"{case} ({what}):\n{result.output}"
    if result.exit_code == 0:
        assert calls, f"{case} ({what}): exit 0 but no benchmark ran"
        for call in calls:
            if "repeats" in call:
                assert 1 <= call["repeats"] <= 1000 and call["waves"], f"{case} ({what}): {call}"
                assert call["backends"] is None or call["backends"], f"{case} ({what}): {call}"  # None: all here


def folder_digest(folder: Path) -> dict[str, str]:
    """Every file under `folder` by relative path -> its bytes' hash (what a refused command must leave alone)."""
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


REFUSED_TRAIN = {"--model": MODELS, "--num-primitives": NUMBERS, "--max-primitives": NUMBERS, "--backend": BACKENDS,
                 "--nproc": ["-1", "0", "nan", "abc", "1e308", "99999999999999999999999", ""],  # 2 would train "--resolution": NUMBERS, "--test-every": NUMBERS, "--background": BACKGROUNDS,
                 "--n-waves": NUMBERS, "--store": ["4bit", "float16", "8bit", "x", ""], "--max-bytes": NUMBERS,
                 "--init-from": ["absent.ply", "model.pt"], "--strategy": ["mcmc", "x"], "--resume": None}


def fuzz_refused_train(case, rng, seeds, tmp, monkeypatch):
    """`train --overwrite` into a finished run with options mutated: a refused command leaves every file of the run
    byte-identical; one that is not refused trains a new run there (two iterations)."""
    from splatzoo.cli import app

    monkeypatch.chdir(tmp)
    shutil.copy(seeds.model_pt[0], tmp / "model.pt")
    run = _copy(seeds.finished, tmp / "run")
    before = folder_digest(run)
    chosen = rng.sample(sorted(REFUSED_TRAIN), k=rng.choice([1, 1, 2]))
    args = ["train", str(rng.choice([seeds.data, seeds.data, tmp / "absent"])), "--out", str(run), "--iterations",
            "2", "--overwrite"]
    for option in chosen:
        values = REFUSED_TRAIN[option]
        args += [option] if values is None else [option, rng.choice(values)]
    what = " ".join(a if len(a) < 60 else a[:20] + "..." for a in args)
    result = outcome(case, what, lambda: CliRunner().invoke(app, args))
    if result.exception is not None and not isinstance(result.exception, (SystemExit, SplatzooError)):
        pytest.fail(f"{case} ({what}): {type(result.exception).__name__}, not a SplatzooError\n"
                    + "".join(traceback.format_exception(*result.exc_info)), pytrace=False)
    assert "Traceback" not in result.output, f"{case} ({what}):\n{result.output}"
    if result.exit_code != 0:
        assert folder_digest(run) == before, f"{case} ({what}): refused, but the run folder changed"


FUZZ = {"ply-binary": fuzz_ply_binary, "ply-ascii": fuzz_ply_ascii, "model-pt": fuzz_model_pt,
        "checkpoint": fuzz_checkpoint, "run-config": fuzz_run_config, "colmap-bin": fuzz_colmap_bin,
        "colmap-txt": fuzz_colmap_txt, "blender-json": fuzz_blender_json, "images": fuzz_images,
        "points-ply": fuzz_points_ply, "ply-variants": fuzz_ply_variants, "distortion": fuzz_distortion,
        "init-from": fuzz_init_from, "option-strings": fuzz_option_strings}


def test_fuzz(fuzz_case, seeds, tmp_path, monkeypatch, request):
    target = fuzz_case.rsplit("-", 1)[0]
    rng = random.Random(fuzz_case)
    if target == "cli":
        fuzz_cli(fuzz_case, rng, seeds, tmp_path, monkeypatch)
    elif target == "refused-train":
        fuzz_refused_train(fuzz_case, rng, seeds, tmp_path, monkeypatch)
    elif target == "bench":
        fuzz_bench(fuzz_case, rng, seeds, tmp_path, monkeypatch)
    elif target in ("ply-variants", "init-from"):
        FUZZ[target](fuzz_case, rng, seeds, tmp_path, request.getfixturevalue("ply_variants"))
    elif target == "splat-formats":
        fuzz_splat_formats(fuzz_case, rng, seeds, tmp_path, request.getfixturevalue("splat_files"))
    else:
        FUZZ[target](fuzz_case, rng, seeds, tmp_path)


def test_the_seeds_themselves_load(seeds, tmp_path, request):
    """Every seed is valid: a case that refuses it is a mutation at work, not a broken seed."""
    from splatzoo.export import load_ply, load_source
    from splatzoo.runs import Run, train
    from splatzoo.training import TrainConfig
    from splatzoo.zoo import load_model

    for path in seeds.model_pt:
        valid_model(load_model(path))
    valid_model(load_ply(seeds.ply_binary))
    valid_model(load_ply(seeds.ply_ascii))
    for path in request.getfixturevalue("ply_variants").values():
        valid_model(load_source(path)[0])
    try:
        splats = request.getfixturevalue("splat_files")
    except pytest.skip.Exception:
        splats = {}
    for path in splats.values():
        _distinct_positions(load_source(path)[0])
    for path in (seeds.ply_binary, seeds.model_pt[0]):
        trained = train(seeds.data, None, None, TrainConfig(iterations=2, backend="reference"), tmp_path / path.name,
                        init_from=path, progress=False, evaluate_at_end=False)
        valid_model(trained.model)
    for root in (seeds.data, seeds.colmap_bin, seeds.colmap_txt, seeds.blender, seeds.nerfstudio):
        valid_scene(load_and_decode(root)())
    model, scene, _ = Run(seeds.finished).load()
    valid_model(model)
    valid_scene(scene)
    run = _copy(seeds.run, tmp_path / "run")
    result = _resume(run)()
    valid_model(result.model)


# --- known cases --------------------------------------------------------------------------------------------------
# Inputs that were once accepted silently, crashed with another exception or hung. Already covered elsewhere (not
# repeated here): checkpoint iteration past the end or -1, view_order out of range or huge, Adam state of another
# shape or missing, recent_error "x", a meta tensor in model.pt, a hand-edited config.json with a number for data or a
# string for scene_options (test_runs.py); COLMAP camera width 0, fx 1e-300, a camera of 20000x15000 over small
# images, cx = 1e9, duplicate image names, transforms.json fl_x 5e-324, a 5000-character file_path, a JSON nesting
# bomb, a PNG header claiming 20000x20000 (test_data_inputs.py).

def _expect(error_type, pattern, load):
    """`load()` raises `error_type` matching `pattern`, quickly (no case may hang)."""
    with deadline(CASE_SECONDS), pytest.raises(error_type, match=pattern) as e:
        load()
    return e.value


@pytest.fixture
def colmap_copy(seeds, tmp_path):
    return _copy(seeds.colmap_bin, tmp_path / "d")


def _text_colmap(seeds, tmp_path) -> Path:
    return _copy(seeds.colmap_txt, tmp_path / "t")


def _set_fields(path: Path, first: int, values: list[str]) -> None:
    """Replace the fields first.. of the first data line of a COLMAP text file."""
    lines = path.read_text().splitlines()
    i = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    parts = lines[i].split()
    parts[first:first + len(values)] = values
    lines[i] = " ".join(parts)
    path.write_text("\n".join(lines) + "\n")


def test_colmap_cameras_bin_truncated_to_7_bytes(colmap_copy):
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    cameras = colmap_copy / "sparse" / "0" / "cameras.bin"
    cameras.write_bytes(cameras.read_bytes()[:7])
    _expect(DataError, r"cameras\.bin is damaged or truncated \(the number of cameras needs 8 bytes.*only 7",
            lambda: load_scene(colmap_copy))


@pytest.mark.parametrize("file, edit, message", [
    # pycolmap reserved memory for these counts or read an ended stream for minutes, then std::bad_alloc
    ("points3D.bin", lambda b: struct.pack("<Q", 2**40) + b[8:], r"declares 1099511627776 3D points"),
    ("images.bin", lambda b: b[:8] + b"\xff" * 4 + b[12:], r"unordered_map"),  # an image id no frame has
    ("images.bin", lambda b: b[:b.index(b"view_002.png") + 4], r"image 3's name runs to the end of the file"),
    ("images.bin", lambda b: b.replace(b"view_000.png", b"view\xff000.png"), r"image 1's name .* is not UTF-8"),
    ("cameras.bin", lambda b: b[:12] + struct.pack("<i", 99) + b[16:], r"camera model id 99"),
    ("frames.bin", lambda b: b[:215], r"frames\.bin is damaged or truncated"),
    ("rigs.bin", lambda b: b + b"\0", r"1 bytes follow the last entry"),
])
def test_colmap_binary_counts_are_checked_before_pycolmap_reads_them(colmap_copy, file, edit, message):
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    path = colmap_copy / "sparse" / "0" / file
    path.write_bytes(edit(path.read_bytes()))
    e = _expect(DataError, message, lambda: load_scene(colmap_copy))
    assert f"cannot read COLMAP model {path.parent}" in str(e)


@pytest.mark.parametrize("entries, message", [({"fx": 0.0}, "focal fx = 0 px"), ({"fx": -50.0}, "focal fx = -50 px"),
                                              ({"fy": 0.0}, "focal fy = 0 px")])
def test_colmap_focal_zero_or_negative(tmp_path, entries, message):
    from test_data_inputs import _colmap_with, _with_K

    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    root = _colmap_with(tmp_path, lambda cams, names: ([_with_K(cams[0], **entries)] + cams[1:], names))
    _expect(DataError, re.escape(message), lambda: load_scene(root))


@pytest.mark.parametrize("where", ["frames.txt", "images.txt of a model without rigs and frames"])
def test_colmap_zero_quaternion_is_named_not_the_identity(seeds, tmp_path, where):
    """A zero quaternion made the identity rotation, silently."""
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    root = _text_colmap(seeds, tmp_path)
    sparse = root / "sparse" / "0"
    if where == "frames.txt":
        _set_fields(sparse / "frames.txt", 2, ["0", "0", "0", "0"])
    else:
        (sparse / "frames.txt").unlink()
        (sparse / "rigs.txt").unlink()
        _set_fields(sparse / "images.txt", 1, ["0", "0", "0", "0"])
    _expect(DataError, r"has a broken pose \(its rotation quaternion \[0.0, 0.0, 0.0, 0.0\].*length 0",
            lambda: load_scene(root))
    _set_fields(sparse / ("frames.txt" if where == "frames.txt" else "images.txt"), 2 if where == "frames.txt"
                else 1, ["1", "0", "0", "0"])
    valid_scene(load_scene(root))  # a unit quaternion loads


def test_colmap_point_with_nan_position(colmap_copy):
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    points = colmap_copy / "sparse" / "0" / "points3D.bin"
    data = bytearray(points.read_bytes())
    data[16:24] = struct.pack("<d", float("nan"))  # after the count and the first point's id: its x
    points.write_bytes(bytes(data))
    _expect(DataError, r"1 3D point\(s\) have a non-finite or out-of-range position", lambda: load_scene(colmap_copy))


@pytest.mark.parametrize("change, message", [
    (lambda m: m["frames"][1]["transform_matrix"][1].__setitem__(0, 10**400), r"holds NaN or infinity \(or a number "
                                                                               r"too large for a float\)"),
    (lambda m: m.update(camera_angle_x=10**400), r"camera_angle_x is 1000.*not a finite number"),
])
def test_transforms_integers_too_large_for_a_float(seeds, tmp_path, change, message):
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    root = _copy(seeds.blender, tmp_path / "b")
    meta = json.loads((root / "transforms_train.json").read_text())
    change(meta)
    (root / "transforms_train.json").write_text(json.dumps(meta))
    _expect(DataError, message, lambda: load_scene(root))


@pytest.mark.parametrize("options, message", [({"test_every": "x"}, r"test_every='x' is not allowed"),
                                              ({"test_every": 2.5}, r"test_every=2.5"),
                                              ({"max_width": "wide"}, r"max_width='wide' must be"),
                                              ({"max_width": 10**400}, r"max_width=1000"),
                                              ({"resolution": 2.0}, r"resolution=2.0 is not supported"),
                                              ({"background": [10**400, 0, 0]}, r"background \[1000")])
def test_load_scene_options_of_the_wrong_type(seeds, options, message):
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    _expect(DataError, message, lambda: load_scene(seeds.colmap_bin, **options))


def _resume_with(seeds, tmp_path, edit):
    run = _copy(seeds.run, tmp_path / "run")
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    edit(state)
    torch.save(state, run / "checkpoint.pt")
    return run


def _group(state, i):
    return state["optimizer"]["param_groups"][i]


@pytest.mark.parametrize("edit, message", [
    (lambda s: _group(s, 1).update(betas=-1), r"betas of optimizer group 'log_scales' is -1"),
    (lambda s: _group(s, 1).update(betas=(0.9, 10**39)), r"betas of optimizer group"),
    (lambda s: _group(s, 1).pop("betas"), r"betas is missing from optimizer group"),
    (lambda s: _group(s, 2).update(lr=[]), r"lr of optimizer group 'quats' is \[\]"),
    (lambda s: _group(s, 2).update(lr=1e308), r"lr of optimizer group 'quats' is 1e\+308, but the run gives it 0.001"),
    (lambda s: _group(s, 2).update(name="quats_x"), r"optimizer group 'quats_x' is not one of the model's"),
    (lambda s: _group(s, 0).update(eps=10**30), r"eps of optimizer group 'means'"),
    (lambda s: _group(s, 0).update(weight_decay=1e308), r"weight_decay of optimizer group 'means'"),
    (lambda s: _group(s, 0).update(capturable=True), r"capturable of optimizer group 'means' is True"),
    (lambda s: _group(s, 0).update(maximize=True), r"maximize of optimizer group 'means' is True"),
    (lambda s: s["optimizer"]["state"][1].update(step=torch.tensor(True)), r"Adam's step of parameter 1 is"),
    (lambda s: s["densify"].update(count={"a": 1}), r"densification statistics: 'count' is a dict"),
    (lambda s: s.update(view_order=[10**400]), r"view_order names view 100000000000\.\.\. \(401 digits\), but the "
                                                 r"dataset has 3 training views"),
])
def test_checkpoint_adam_hyperparameters_are_checked_before_training(seeds, tmp_path, edit, message):
    """torch loads an optimizer's hyperparameters unchecked and fails (or climbs the loss) only at the next step."""
    run = _resume_with(seeds, tmp_path, edit)
    _expect(SplatzooError, r"does not hold a consistent training state .*" + message, _resume(run))
    assert not (run / "model.pt").exists()


def test_a_run_that_diverges_writes_no_checkpoint_or_model(seeds, tmp_path):
    """A finite but absurd Adam moment made the next step's opacities infinite, and they were saved as the model."""
    def huge_moment(state):
        groups = [g["name"] for g in state["optimizer"]["param_groups"]]
        moment = state["optimizer"]["state"][groups.index("logit_opacity")]
        moment["exp_avg"] = torch.full_like(moment["exp_avg"], 3e38)

    run = _resume_with(seeds, tmp_path, huge_moment)
    kept = (run / "checkpoint.pt").read_bytes()
    _expect(SplatzooError, r"the run diverged: logit_opacity became NaN or infinite by iteration 3; nothing was "
                           r"written", _resume(run))
    assert (run / "checkpoint.pt").read_bytes() == kept and not (run / "model.pt").exists()


@pytest.mark.parametrize("edit, message", [  # the scene options are checked when the record is read, the rest on use
    (lambda r: r["scene_options"].update(test_every="a" * 40), r"scene option test_every='aaa"),
    (lambda r: r["scene_options"].update(resolution=3), r"scene option resolution=3 is not supported"),
    (lambda r: r["scene_options"].update(background=[10**400, 0, 0]), r"scene option background"),
    (lambda r: r["scene_options"].update(colour="red"), r"unknown scene option\(s\) 'colour'"),
    (lambda r: r["train"].update(batch_size=2.5), r"batch_size must be int, got 2.5"),
    (lambda r: r["train"].update(seed=1.5), r"seed must be int, got 1.5"),
    (lambda r: r["train"].update(iterations=10**400), r"iterations must be int, got 1000"),
    (lambda r: r["train"].update(densify="yes"), r"densify must be bool"),
    (lambda r: r["train"].update(num_primitives="many"), r"num_primitives must be int or null"),
    (lambda r: r.update(data="a" * 5000), r"cannot be looked up \(File name too long\); the run configuration"),
])
def test_hand_edited_run_config_types(seeds, tmp_path, edit, message):
    from splatzoo.runs import Run

    run = _copy(seeds.run, tmp_path / "run")
    record = json.loads((run / "config.json").read_text())
    edit(record)
    (run / "config.json").write_text(json.dumps(record))
    e = _expect(SplatzooError, message, _resume(run, stop_after=0))
    assert "config.json" in str(e)
    if "scene option" in message:
        _expect(SplatzooError, message, lambda: Run(run).record())


def test_run_config_nesting_bomb(seeds, tmp_path):
    run = _copy(seeds.run, tmp_path / "run")
    (run / "config.json").write_text('{"train": ' + "[" * 100_000 + "]" * 100_000 + "}")
    _expect(SplatzooError, r"config\.json is damaged \(its JSON nests too deeply\)", _resume(run))


def test_model_config_number_too_large_for_a_float(seeds, tmp_path):
    from splatzoo.zoo import load_model

    ckpt = torch.load(seeds.model_pt[0], weights_only=True)
    ckpt["config"]["prune_waves"] = 10**400
    torch.save(ckpt, tmp_path / "model.pt")
    _expect(SplatzooError, r"config option prune_waves of model 'gabor' is 1000.*too large for a float",
            lambda: load_model(tmp_path / "model.pt"))


@pytest.mark.parametrize("width", [torch.tensor(3e38), torch.tensor(10 ** 9), torch.tensor(-1)])
def test_packed_wave_width_too_large(seeds, tmp_path, width):
    """A pruned model's wave width of 3e38 (a float where a count belongs) overflowed in the model's own loader, and
    one of 1e9 sized arrays of gigabytes: the width is checked against n_waves first."""
    from splatzoo.zoo import load_model

    ckpt = torch.load(seeds.model_pt[1], weights_only=True)
    ckpt["state"]["wave_width"] = width
    torch.save(ckpt, tmp_path / "model.pt")
    _expect(SplatzooError, r"its state does not fit model 'gabor'.*wave_width\) must be a whole number in 0\.\.n_waves",
            lambda: load_model(tmp_path / "model.pt"))


def test_paths_longer_than_the_file_system_allows(seeds, tmp_path, monkeypatch):
    """Path.exists() and friends raise OSError (ENAMETOOLONG) instead of answering: a named error everywhere."""
    from splatzoo.cli import app
    from splatzoo.data import load_scene
    from splatzoo.export import load_ply
    from splatzoo.runs import Run
    from splatzoo.zoo import load_model

    long = tmp_path / ("x" * 300)
    for load in (lambda: load_model(long), lambda: load_ply(long), lambda: Run(long).status,
                 lambda: load_scene(long)):
        _expect(SplatzooError, r"cannot be (looked up|read) \(File name too long\)", load)
    monkeypatch.chdir(tmp_path)
    for args in (["eval", str(long)], ["export", str(seeds.finished), "--out", str(long) + ".ply"],
                 ["train", str(long), "--out", str(tmp_path / "out")], ["view", str(long)]):
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 2 and "cannot be looked up (File name too long)" in result.output, result.output


# --- PLY bodies must be what their headers declare -------------------------------------------------------------

def _split(path: Path) -> tuple[str, bytes]:
    header, body = path.read_bytes().split(b"end_header\n", 1)
    return header.decode() + "end_header\n", body


def test_ply_vertex_count_smaller_than_the_body(seeds, tmp_path):
    from splatzoo.export import load_ply

    header, body = _split(seeds.ply_binary)
    count = int(re.search(r"element vertex (\d+)", header).group(1))
    size = len(body) // count
    path = tmp_path / "m.ply"
    path.write_bytes(header.replace(f"element vertex {count}", f"element vertex {count - 2}").encode() + body)
    _expect(SplatzooError, rf"m\.ply: the header promises {count - 2} vertices of {size} bytes = "
                           rf"{(count - 2) * size} bytes but {len(body)} bytes follow; the count is wrong or the file "
                           r"is damaged\. Export the model again", lambda: load_ply(path))
    path.write_bytes(header.encode() + body + b"\n")  # one stray byte after a whole body
    _expect(SplatzooError, rf"but {len(body) + 1} bytes follow", lambda: load_ply(path))
    # with a second fixed-size element the sum of both is what must follow
    two = header.replace("end_header", "element extra 2\nproperty uchar flag\nend_header")
    path.write_bytes(two.encode() + body + b"\x01\x02")
    valid_model(load_ply(path))
    path.write_bytes(two.encode() + body + b"\x01\x02\x03")
    _expect(SplatzooError, rf"{count} vertices of {size} bytes and 2 extra of 1 bytes = {len(body) + 2} bytes",
            lambda: load_ply(path))
    # a list property (a mesh's faces) cannot be sized cheaply: the vertices must be there, the rest is not checked
    mesh = header.replace("end_header", "element face 1\nproperty list uchar int vertex_indices\nend_header")
    path.write_bytes(mesh.encode() + body + b"\x03" + struct.pack("<3i", 0, 1, 2))
    valid_model(load_ply(path))


def test_ascii_ply_with_more_rows_than_its_count(seeds, tmp_path):
    from splatzoo.export import load_ply

    header, body = _split(seeds.ply_ascii)
    rows = body.decode().strip().splitlines()
    path = tmp_path / "m.ply"
    path.write_text(header.replace(f"element vertex {len(rows)}", f"element vertex {len(rows) - 1}") + body.decode())
    _expect(SplatzooError, rf"promises {len(rows) - 1} vertices but {len(rows)} rows follow; the count is wrong",
            lambda: load_ply(path))
    path.write_text(header + body.decode() + "\n\n")  # blank lines at the end are no rows
    valid_model(load_ply(path))


@pytest.mark.parametrize("kind", ["int", "uchar", "short"])
def test_integer_property_over_float_data(seeds, tmp_path, kind):
    """`property int x` over float bytes read the float's bits as integers: a model with its points far away."""
    from splatzoo.export import load_ply

    header, body = _split(seeds.ply_binary)
    size = {"int": 4, "uchar": 1, "short": 2}[kind]
    count = int(re.search(r"element vertex (\d+)", header).group(1))
    props = re.findall(r"property float (\S+)", header)
    # the body stays consistent with the header: the changed property takes `size` bytes in every row
    columns = np.frombuffer(body, "<f4").reshape(count, len(props))
    i = props.index("scale_0")
    data = b"".join(columns[r, :i].tobytes() + bytes(size) + columns[r, i + 1:].tobytes() for r in range(count))
    path = tmp_path / "m.ply"
    path.write_bytes(header.replace("property float scale_0", f"property {kind} scale_0").encode() + data)
    _expect(SplatzooError, rf"m\.ply: scale_0 is stored as {kind} but holds a float parameter \('log_scales'\); the "
                           r"file was not written by splatzoo export or is damaged", lambda: load_ply(path))


def test_real_2dgs_and_3dgs_layouts_are_all_float(seeds, tmp_path):
    """What 2DGS / 3DGS write (plyfile, every attribute 'f4'), read back: x..rot_3 as float, also as double."""
    from splatzoo.export import load_ply

    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
             + ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"])
    g = np.random.default_rng(0)
    for kind, dtype in (("float", "<f4"), ("double", "<f8")):
        values = g.normal(size=(5, len(props))).astype(dtype)
        header = ("ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
                  + "".join(f"property {kind} {p}\n" for p in props) + "end_header\n")
        path = tmp_path / f"{kind}.ply"
        path.write_bytes(header.encode() + values.tobytes())
        model = load_ply(path)
        assert model.name == "2dgs" and model.num_primitives == 5
        valid_model(model)


def _points(seeds, tmp_path, header_edit=None, body=None) -> Path:
    root = _copy(seeds.nerfstudio, tmp_path / "ns")
    ply = root / "sparse_pc.ply"
    header, data = _split(ply)
    ply.write_bytes((header_edit(header) if header_edit else header).encode() + (data if body is None else body))
    return root


def test_point_cloud_checks(seeds, tmp_path):
    """read_ply_points: counts match the body, positions are floats and finite, uchar colours still work."""
    from splatzoo.data import load_scene
    from splatzoo.errors import DataError

    scene = load_scene(_points(seeds, tmp_path / "a"))  # uchar colours: the normal case
    assert scene.points.shape == (16, 3) and float(scene.colors.max()) <= 1 and float(scene.colors.max()) > 0.5
    _, body = _split(seeds.nerfstudio / "sparse_pc.ply")
    root = _points(seeds, tmp_path / "b", lambda h: h.replace("element vertex 16", "element vertex 15"))
    _expect(DataError, r"promises 15 vertices of 15 bytes = 225 bytes but 240 bytes follow.*Fix or delete it",
            lambda: load_scene(root))
    root = _points(seeds, tmp_path / "c", lambda h: h.replace("element vertex 16", f"element vertex {2**64 + 3}"))
    _expect(DataError, r"sparse_pc\.ply is truncated", lambda: load_scene(root))
    root = _points(seeds, tmp_path / "d", lambda h: h.replace("property uchar blue\n", ""))
    _expect(DataError, r"the count is wrong or the file is damaged", lambda: load_scene(root))
    root = _points(seeds, tmp_path / "e", lambda h: h.replace("property float x", "property int x"))
    _expect(DataError, r"x is stored as int; point positions are float or double", lambda: load_scene(root))
    nan = bytearray(body)
    nan[4:8] = struct.pack("<f", float("nan"))
    root = _points(seeds, tmp_path / "f", body=bytes(nan))
    _expect(DataError, r"1 point\(s\) have a non-finite or out-of-range position", lambda: load_scene(root))
    ascii_root = _points(seeds, tmp_path / "g", lambda h: h.replace("binary_little_endian", "ascii"),
                         body=b"0 0 0 -2147483649 0 0\n" * 16)
    _expect(DataError, r"the uchar property red holds values that are not whole numbers in 0\.\.255",
            lambda: load_scene(ascii_root))
    floats = "ply\nformat ascii 1.0\nelement vertex 2\n" + "".join(
        f"property {t} {p}\n" for t, p in (("double", "x"), ("double", "y"), ("double", "z"), ("float", "red"),
                                           ("float", "green"), ("float", "blue"))) + "end_header\n"
    root = _points(seeds, tmp_path / "h")
    (root / "sparse_pc.ply").write_text(floats + "0 0 0 0.5 0.5 0.5\n1 1 1 1 0 0\n")
    scene = load_scene(root)
    assert torch.allclose(scene.colors, torch.tensor([[0.5, 0.5, 0.5], [1.0, 0, 0]]))
