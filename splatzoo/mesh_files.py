"""Mesh files: `TexturedMesh` (a triangle mesh with UVs and a texture, or vertex colours) and every writer of a mesh
file, under both splatzoo.mesh (which extracts meshes) and splatzoo.mesh_texture (which textures them).

`write_glb` (pygltflib; positions, normals, UVs or vertex colours; accessor min/max; a PBR material with the texture as
baseColorTexture, metallic 0, roughness 1, double sided, and KHR_materials_unlit so viewers show the baked colour as it
is instead of lighting it a second time), `write_obj` (text OBJ with `mtllib` and `map_Kd` naming the .mtl and .png
beside it by relative name), `write_textured_mesh` (either, by suffix) and `write_mesh` (an open3d mesh: PLY and the
other formats open3d writes, OBJ and GLB through the writers here). Every file is written atomically. open3d,
pygltflib and pillow are imported inside the functions that need them.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SplatzooError
from .io import atomic_path


@dataclass
class TexturedMesh:
    """A triangle mesh ready to write. positions [V,3] float32, faces [F,3] int64 (wound as the mesh came; the GLB
    material is double sided), normals [V,3] or None, uvs [V,2] float32 in [0,1] (glTF convention: v = 0 is the
    top row of the texture) or None, texture [H,W,3] uint8 or None, colors [V,3] float32 in [0,1] (vertex
    colours) or None. With a texture the vertex colours are not written (glTF would multiply them into it)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    colors: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @classmethod
    def from_open3d(cls, mesh) -> "TexturedMesh":
        """An open3d legacy TriangleMesh (vertex colours and normals kept when present)."""
        pos = np.asarray(mesh.vertices, dtype=np.float32)
        faces = np.asarray(mesh.triangles, dtype=np.int64).reshape(-1, 3)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float32) if mesh.has_vertex_normals() else None
        colors = np.asarray(mesh.vertex_colors, dtype=np.float32) if mesh.has_vertex_colors() else None
        return cls(pos, faces, normals=normals, colors=colors)

    def check(self) -> "TexturedMesh":
        V = len(self.positions)
        if self.positions.ndim != 2 or self.positions.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise SplatzooError("a mesh needs positions [V,3] and faces [F,3]")
        if len(self.faces) == 0 or V == 0:
            raise SplatzooError("the mesh is empty (no triangles); nothing to write")
        if self.faces.min() < 0 or self.faces.max() >= V:
            raise SplatzooError(f"mesh faces index vertices outside 0..{V - 1}")
        if not np.isfinite(self.positions).all():
            raise SplatzooError("mesh positions must be finite")
        for name, width in (("normals", 3), ("uvs", 2), ("colors", 3)):
            a = getattr(self, name)
            if a is not None and a.shape != (V, width):
                raise SplatzooError(f"mesh {name} must be [{V},{width}], got {list(a.shape)}")
        if (self.texture is None) != (self.uvs is None):
            raise SplatzooError("a textured mesh needs both uvs and a texture")
        if self.texture is not None and (self.texture.ndim != 3 or self.texture.shape[2] != 3
                                         or self.texture.dtype != np.uint8):
            raise SplatzooError("the texture must be an [H,W,3] uint8 image")
        return self



def png_bytes(texture: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(texture), "RGB").save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def glb_bytes(mesh: TexturedMesh, *, unlit: bool = True) -> bytes:
    """The mesh as a binary glTF 2.0: one buffer (the GLB's binary chunk) holding indices, positions, normals,
    UVs or vertex colours, and the PNG texture; accessor min/max set; one material."""
    import pygltflib as g

    mesh.check()
    blob = bytearray()
    views: list = []
    accessors: list = []

    def add_view(data: bytes, target=None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    def add_accessor(a: np.ndarray, type_: str, component, target, *, minmax: bool = True) -> int:
        view = add_view(np.ascontiguousarray(a).tobytes(), target)
        acc = g.Accessor(bufferView=view, byteOffset=0, componentType=component, count=int(len(a)), type=type_)
        if minmax:
            flat = a.reshape(len(a), -1)
            if a.dtype.kind in "ui":
                acc.min, acc.max = [int(v) for v in flat.min(0)], [int(v) for v in flat.max(0)]
            else:
                acc.min, acc.max = [float(v) for v in flat.min(0)], [float(v) for v in flat.max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    index_array = mesh.faces.astype(np.uint32).reshape(-1)
    indices = add_accessor(index_array, g.SCALAR, g.UNSIGNED_INT, g.ELEMENT_ARRAY_BUFFER)
    attrs = g.Attributes(POSITION=add_accessor(mesh.positions.astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER))
    if mesh.normals is not None:
        n = mesh.normals.astype(np.float32)
        n = n / np.where(np.linalg.norm(n, axis=1, keepdims=True) > 0, np.linalg.norm(n, axis=1, keepdims=True), 1)
        attrs.NORMAL = add_accessor(n.astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER)
    material = g.Material(name="splatzoo", doubleSided=True,
                          pbrMetallicRoughness=g.PbrMetallicRoughness(metallicFactor=0.0, roughnessFactor=1.0))
    gltf = g.GLTF2(asset=g.Asset(version="2.0", generator="splatzoo"), scene=0)
    if mesh.texture is not None:
        attrs.TEXCOORD_0 = add_accessor(mesh.uvs.astype(np.float32), g.VEC2, g.FLOAT, g.ARRAY_BUFFER)
        image_view = add_view(png_bytes(mesh.texture))
        gltf.images = [g.Image(bufferView=image_view, mimeType="image/png")]
        gltf.samplers = [g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE,
                                   wrapT=g.CLAMP_TO_EDGE)]
        gltf.textures = [g.Texture(sampler=0, source=0)]
        material.pbrMetallicRoughness.baseColorTexture = g.TextureInfo(index=0)
    elif mesh.colors is not None:
        attrs.COLOR_0 = add_accessor(np.clip(mesh.colors, 0, 1).astype(np.float32), g.VEC3, g.FLOAT, g.ARRAY_BUFFER)
    if unlit:
        material.extensions = {"KHR_materials_unlit": {}}
        gltf.extensionsUsed = ["KHR_materials_unlit"]
    gltf.materials = [material]
    gltf.meshes = [g.Mesh(name="splatzoo", primitives=[g.Primitive(attributes=attrs, indices=indices, material=0,
                                                                   mode=g.TRIANGLES)])]
    gltf.nodes = [g.Node(mesh=0, name="splatzoo")]
    gltf.scenes = [g.Scene(nodes=[0])]
    while len(blob) % 4:
        blob.append(0)
    gltf.bufferViews = views
    gltf.accessors = accessors
    gltf.buffers = [g.Buffer(byteLength=len(blob))]
    gltf.set_binary_blob(bytes(blob))
    return b"".join(gltf.save_to_bytes())


def write_glb(mesh: TexturedMesh, path, *, unlit: bool = True) -> Path:
    """Write the mesh as .glb atomically."""
    path = Path(path)
    data = glb_bytes(mesh, unlit=unlit)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _rows(fmt: str, a: np.ndarray) -> str:
    """One line per row of a, formatted with fmt (numpy's savetxt, without a file)."""
    import io

    buf = io.StringIO()
    np.savetxt(buf, a, fmt=fmt)
    return buf.getvalue()


def obj_companions(path) -> tuple[Path, Path]:
    """The material and texture files a textured OBJ names beside itself: <stem>.mtl and <stem>.png."""
    path = Path(path)
    mtl, png = path.with_suffix(".mtl"), path.with_suffix(".png")
    if path in (mtl, png):
        raise SplatzooError(f"{path}: the OBJ needs a .obj suffix so its .mtl and .png get their own names")
    return mtl, png


def _head(path: Path, size: int = 4096) -> str:
    """The start of a regular file as text ('' for anything else or on any error)."""
    try:
        if not path.is_file():
            return ""
        with open(path, "rb") as f:
            return f.read(size).decode("utf-8", "replace")
    except OSError:
        return ""


def check_obj_companions(path) -> None:
    """Refuse to write a textured OBJ whose .mtl or .png name is taken by a file that is not the material or texture
    of the OBJ already at `path` (one written here before, which the new OBJ replaces together with them). Run before
    anything is written, so a refusal leaves every file as it was."""
    path = Path(path)
    mtl, png = obj_companions(path)
    obj_head, mtl_head = _head(path), _head(mtl)
    own_mtl = obj_head.startswith("# splatzoo mesh") and f"\nmtllib {mtl.name}\n" in obj_head
    own = {mtl: own_mtl and mtl_head.startswith("# splatzoo material"),
           png: own_mtl and mtl_head.startswith("# splatzoo material") and f"\nmap_Kd {png.name}\n" in mtl_head}
    taken = [p for p in (mtl, png) if (p.exists() or p.is_symlink()) and not (own[p] and p.is_file())]
    if taken:
        names = " and ".join(str(p) for p in taken)
        raise SplatzooError(f"the OBJ {path} names its material and texture {mtl.name} and {png.name} beside it, but "
                            f"{names} already exist{'s' if len(taken) == 1 else ''} and "
                            f"{'is' if len(taken) == 1 else 'are'} not the material or texture of an OBJ exported to "
                            f"{path.name}; move {'it' if len(taken) == 1 else 'them'} away or choose another --out "
                            f"name (nothing was written)")


def write_obj(mesh: TexturedMesh, path) -> Path:
    """Write the mesh as a text OBJ atomically. With a texture: `<stem>.mtl` and `<stem>.png` beside it, named
    relatively in the OBJ (mtllib) and the MTL (map_Kd), written before the OBJ. Without one: vertex colours as
    `v x y z r g b` (the extension open3d, trimesh and MeshLab read)."""
    path = Path(path)
    mesh.check()
    parts = ["# splatzoo mesh\n", f"# {len(mesh.positions)} vertices, {len(mesh.faces)} triangles\n"]
    f = mesh.faces.astype(np.int64) + 1
    if mesh.texture is not None:
        mtl, png = obj_companions(path)
        check_obj_companions(path)
        with atomic_path(png) as tmp:
            tmp.write_bytes(png_bytes(mesh.texture))
        with atomic_path(mtl) as tmp:
            tmp.write_text("# splatzoo material\nnewmtl splatzoo\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
                           f"map_Kd {png.name}\n")
        parts.append(f"mtllib {mtl.name}\nusemtl splatzoo\n")
    if mesh.colors is not None and mesh.texture is None:
        parts.append(_rows("v %.7g %.7g %.7g %.5f %.5f %.5f",
                           np.concatenate([mesh.positions, np.clip(mesh.colors, 0, 1)], 1).astype(np.float64)))
    else:
        parts.append(_rows("v %.7g %.7g %.7g", mesh.positions.astype(np.float64)))
    if mesh.texture is not None:
        uv = mesh.uvs.astype(np.float64).copy()
        uv[:, 1] = 1.0 - uv[:, 1]   # OBJ's v points up the image, glTF's down
        parts.append(_rows("vt %.7g %.7g", uv))
    if mesh.normals is not None:
        parts.append(_rows("vn %.6g %.6g %.6g", mesh.normals.astype(np.float64)))
    if mesh.texture is not None and mesh.normals is not None:
        parts.append(_rows("f %d/%d/%d %d/%d/%d %d/%d/%d", np.repeat(f, 3, axis=1)))
    elif mesh.texture is not None:
        parts.append(_rows("f %d/%d %d/%d %d/%d", np.repeat(f, 2, axis=1)))
    elif mesh.normals is not None:
        parts.append(_rows("f %d//%d %d//%d %d//%d", np.repeat(f, 2, axis=1)))
    else:
        parts.append(_rows("f %d %d %d", f))
    with atomic_path(path) as tmp:
        tmp.write_text("".join(parts))
    return path


def write_textured_mesh(mesh: TexturedMesh, out, *, unlit: bool = True) -> Path:
    """.glb or .obj (+ .mtl + .png) by the suffix of `out`."""
    out = Path(out)
    suffix = out.suffix.lower()
    if out.is_dir():
        raise SplatzooError(f"cannot write the mesh to {out}: it is a folder; give a file name such as "
                            f"{out / 'mesh.glb'}")
    if suffix == ".glb":
        return write_glb(mesh, out, unlit=unlit)
    if suffix == ".obj":
        return write_obj(mesh, out)
    raise SplatzooError(f"{out}: a textured mesh is written as .glb (one file) or .obj (with .mtl and .png beside "
                        "it); choose one of these suffixes")


MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb")  # what write_mesh writes (.ply recommended)


def check_mesh_target(path, writable: bool = True) -> Path:
    """Refuse a mesh file name that write_mesh could not write, before any mesh is made: a folder, a suffix it does
    not write, a place where no file can be made (its nearest existing folder is a file or, with `writable`, not
    writable)."""
    path = Path(path)
    fix = f"give a file name ending in {'/'.join(MESH_SUFFIXES)} in a writable folder"
    if path.is_dir():
        raise SplatzooError(f"cannot write the mesh to {path}: it is a folder; give a file name such as "
                            f"{path / 'mesh.ply'}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SplatzooError(f"{path} is not a mesh file name splatzoo writes ({path.suffix or 'no suffix'}); {fix}")
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise SplatzooError(f"cannot write the mesh to {path}: {folder} is a file, not a folder; {fix}")
    if writable and not os.access(folder, os.W_OK | os.X_OK):
        raise SplatzooError(f"cannot write the mesh to {path}: {folder} is not writable; {fix}")
    return path


def write_mesh(mesh, path) -> Path:
    """Write an open3d legacy TriangleMesh (binary, with vertex colours) atomically; the format follows the
    suffix (.ply recommended).

    .obj and .glb are written by `write_textured_mesh`: open3d's OBJ header names the file it wrote (here the
    temporary name of the atomic write), and its GLB (buffer as a data URI, wrong index bounds) is not read back
    by open3d itself. Vertex colours go into the OBJ as `v x y z r g b` and into the GLB as COLOR_0."""
    import open3d as o3d

    path = check_mesh_target(path)
    if path.suffix.lower() in (".obj", ".glb"):
        if len(mesh.triangles) == 0:
            raise SplatzooError(f"cannot write {path}: the mesh has no triangles")
        return write_textured_mesh(TexturedMesh.from_open3d(mesh), path, unlit=False)
    with atomic_path(path) as tmp:
        ok = o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, write_vertex_colors=True)
        if not ok:
            raise SplatzooError(f"open3d could not write the mesh to {path}; use a .ply (or .obj/.off/.stl/.glb) file "
                                "name in a writable folder with free space")
    return path
