"""Optional Mitsuba 3 interop: the same scene, camera and env map rendered by Mitsuba's integrators.

Used to cross-check `render(T, x)` and to time the user's alternative (one render per column of
`A`). Mitsuba is not a dependency: `pip install mitsuba`; its fast LLVM variant needs a
`libLLVM.so` of version 19 or newer (Debian: `libllvm19`), found automatically or through
`DRJIT_LIBLLVM_PATH`; without one the scalar variant is used.
"""

import glob
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from ..scene import Camera, EnvGrid, Scene
from ..scene._surface import vertex_normals
from ._point_lights import check_lights


# Dr.Jit's LLVM backend aborts the whole process (an LLVM fatal error, not an exception) when the
# library it loads cannot compile its kernels: with drjit 1.5, LLVM 15 and 16 stop at
# "Cannot select: fminimum"; LLVM 19 works (17 and 18 untested).
MIN_LLVM_MAJOR = 19


def llvm_major(path) -> int:
    """Major version of a `libLLVM` shared library from its path (`libLLVM-15.so.1`,
    `libLLVM.so.19.1`, `/usr/lib/llvm-19/lib/libLLVM.so.1`); 0 when the path names none."""
    found = re.findall(r"(?:libLLVM-|libLLVM\.so\.|llvm-)(\d+)", str(path))
    return max((int(v) for v in found), default=0)


def find_llvm() -> str | None:
    """The newest system `libLLVM` of major version >= `MIN_LLVM_MAJOR`, or None."""
    found = glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*")
    usable = [(llvm_major(path), path) for path in found if llvm_major(path) >= MIN_LLVM_MAJOR]
    return max(usable)[1] if usable else None


def mitsuba_variant() -> str:
    """Select and return Mitsuba's variant: `llvm_ad_rgb` with a usable LLVM, else `scalar_rgb`.

    The automatic search takes the newest `libLLVM` of major version >= `MIN_LLVM_MAJOR`; an older
    one would abort the process at the first render, so without a new one the scalar variant is
    used. A `DRJIT_LIBLLVM_PATH` set by the caller is used as given.
    """
    use_llvm = bool(os.environ.get("DRJIT_LIBLLVM_PATH"))
    if not use_llvm and (path := find_llvm()) is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
        use_llvm = True
    import mitsuba as mi

    for variant in (["llvm_ad_rgb"] if use_llvm else []) + ["scalar_rgb"]:
        try:
            mi.set_variant(variant)
            return variant
        except (ImportError, AttributeError):
            continue
    raise ImportError("no usable Mitsuba variant (llvm_ad_rgb or scalar_rgb)")


def upsample_for_mitsuba(envmap, factor: int = 8) -> np.ndarray:
    """Our cell map `(H, W[, C])` -> an RGB bitmap `(kH, kW, 3)` for Mitsuba's `envmap`.

    Mitsuba puts bitmap row `r` at `theta = r pi/(rows - 1)` (docs/conventions.md, "Environment grid"), so each row
    takes the cell containing that angle; a large `factor` keeps cell edges sharp.
    """
    env = np.asarray(envmap, dtype=np.float32)
    env = np.repeat(env[..., None], 3, -1) if env.ndim == 2 else env
    H, W = env.shape[:2]
    rows = factor * H
    theta = np.arange(rows) * np.pi / (rows - 1)
    cell = np.minimum((theta * H / np.pi).astype(int), H - 1)
    return np.ascontiguousarray(np.repeat(env[cell], factor, axis=1))


def _scene_dict(mi, scene: Scene, camera: Camera, folder: Path, integrator: dict) -> dict:
    """Mitsuba's scene dictionary for our surfaces (PLY files written to `folder`), camera and integrator.

    Emitters are the caller's. A glossy surface is Mitsuba's `roughplastic` (GGX, `nonlinear=false`,
    air outside); a smooth one carries its vertex normals in its PLY file (Phong-interpolated there
    too). Constant albedo or a grey texture (Mitsuba's bitmap, bilinear and repeating as `Surface`'s;
    its rows are flipped: Mitsuba puts bitmap row 0 at `v = 0`, ours at `v = 1`); a centred pinhole
    camera with square pixels only.
    """
    fx, fy, cx, cy = np.asarray(camera.intrinsics, dtype=np.float64)
    if not (np.isclose(fx, fy) and np.isclose(cx, camera.width / 2) and np.isclose(cy, camera.height / 2)):
        raise ValueError("Mitsuba export needs square pixels and a centred principal point")
    R = np.asarray(camera.rotation, dtype=np.float64)
    origin = np.asarray(camera.origin, dtype=np.float64)
    shapes = {}
    for k, surface in enumerate(scene):
        if surface.albedo.ndim == 1:
            raise ValueError("Mitsuba export supports a constant albedo or a texture, not per-face albedo")
        if surface.albedo.ndim == 0:
            reflectance = {"type": "rgb", "value": float(surface.albedo)}
        else:
            texture = np.repeat(np.asarray(surface.albedo, np.float32)[::-1, :, None], 3, axis=2)
            reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture)), "raw": True,
                           "filter_type": "bilinear", "wrap_mode": "repeat"}
        path = folder / f"surface{k}.ply"
        mesh = surface.mesh
        if surface.smooth:  # Mitsuba interpolates the file's vertex normals: write ours (it would compute others)
            mesh = mesh.copy()
            mesh.vertex_normals = vertex_normals(surface.mesh)
        mesh.export(path, vertex_normal=surface.smooth)
        bsdf = {"type": "diffuse", "reflectance": reflectance}
        if surface.gloss is not None:  # the same material term by term (scene._gloss)
            bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": surface.gloss.roughness,
                    "int_ior": surface.gloss.ior, "ext_ior": 1.0, "nonlinear": False, "diffuse_reflectance": reflectance}
        shapes[f"surface{k}"] = {
            "type": "ply", "filename": str(path), "face_normals": not surface.smooth,
            # two-sided, as hiddenjax's surfaces are (Embree's normal faces the ray): Mitsuba's diffuse
            # BSDF alone is black from behind, so a mesh wound inward (the teapot) would be black
            "bsdf": {"type": "twosided", "bsdf": bsdf},
        }
    return {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective", "fov": float(np.degrees(2 * np.arctan(camera.width / (2 * fx)))), "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=(origin + R[2]).tolist(),
                                                       up=(-R[1]).tolist()),
            "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        },
        **shapes,
    }


class MitsubaRenderer:
    """A Mitsuba scene built from ours; `render(envmap, spp)` re-lights it without reloading meshes.

    `integrator` is Mitsuba's ('direct' to match `bounces=0`, 'path' with `max_depth` for global
    illumination). Surfaces must have a constant or textured albedo; the camera must be a centred pinhole.
    """

    def __init__(self, scene: Scene, camera: Camera, grid: EnvGrid, integrator: str = "direct",
                 max_depth: int = 4, upsample: int = 8):
        self.variant = mitsuba_variant()
        import mitsuba as mi

        self._mi = mi
        self.grid, self.upsample = grid, upsample
        self._tmp = tempfile.TemporaryDirectory(prefix="hiddenjax-mitsuba-")
        integ = {"type": integrator}
        if integrator == "path":
            integ["max_depth"] = int(max_depth)
        self.scene = mi.load_dict({
            **_scene_dict(mi, scene, camera, Path(self._tmp.name), integ),
            "env": {"type": "envmap", "bitmap": mi.Bitmap(upsample_for_mitsuba(np.ones(grid.shape), upsample))},
        })
        self.params = mi.traverse(self.scene)

    def render(self, envmap, spp: int = 64, seed: int = 0) -> np.ndarray:
        """Render under `envmap (H, W[, 3])` on the grid; returns `(h, w, 3)` float32 radiance."""
        mi = self._mi
        env = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(upsample_for_mitsuba(envmap, self.upsample))})
        self.params["env.data"] = mi.traverse(env)["data"]
        self.params.update()
        return np.array(mi.render(self.scene, spp=spp, seed=seed), dtype=np.float32)


def render_point_lights_mitsuba(scene: Scene, camera: Camera, lights, intensities=None, *, max_depth: int = 4,
                                spp: int = 256, seed: int = 0) -> np.ndarray:
    """`(H, W)` radiance of `scene` under isotropic point lights, path-traced by Mitsuba (all bounces).

    The independent check of the light fits: Mitsuba's `point` emitters (intensity in W/sr, so
    the direct term is `hj.render_point_lights`' `albedo/pi * I * cos / d^2`), its `path`
    integrator with `max_depth` (2: direct light only; 4: up to two diffuse interreflections, the
    table lighting the object and back), a box pixel filter. The channel mean of Mitsuba's RGB
    is returned (grey albedo and white lights). Constant or textured albedo and centred pinhole cameras only.
    """
    lights, intensities = check_lights(lights, intensities)
    mitsuba_variant()
    import mitsuba as mi

    with tempfile.TemporaryDirectory(prefix="hiddenjax-mitsuba-") as tmp:
        emitters = {f"light{k}": {"type": "point", "position": p.tolist(),
                                  "intensity": {"type": "rgb", "value": float(i)}}
                    for k, (p, i) in enumerate(zip(lights, intensities))}
        integrator = {"type": "path", "max_depth": int(max_depth)}
        mscene = mi.load_dict({**_scene_dict(mi, scene, camera, Path(tmp), integrator), **emitters})
        image = np.array(mi.render(mscene, spp=spp, seed=seed), dtype=np.float32)
    return image.mean(axis=-1)


def render_panorama_mitsuba(scene: Scene, camera: Camera, panorama, *, max_depth: int = 3, spp: int = 256,
                            seed: int = 0) -> np.ndarray:
    """`(H, W, 3)` radiance of `scene` under a full-resolution lat-long `panorama (Hf, Wf, 3)`,
    path-traced by Mitsuba (`path` integrator, `max_depth` 3: direct light and one interreflection,
    the table lighting the object and back; 2: direct only).

    The independent photographs of the capture benchmarks: neither `A` nor Embree is involved.
    Mitsuba places bitmap row `r` at `theta = r pi/(Hf - 1)`, half a row off the grid's convention:
    0.2 degrees at 512 rows.
    """
    pano = np.asarray(panorama, dtype=np.float32)
    if pano.ndim == 2:
        pano = np.repeat(pano[..., None], 3, axis=-1)
    if pano.ndim != 3 or pano.shape[-1] != 3 or not np.all(np.isfinite(pano)) or np.any(pano < 0):
        raise ValueError(f"panorama must be finite non-negative radiance (Hf, Wf[, 3]), got shape {pano.shape}")
    mitsuba_variant()
    import mitsuba as mi

    with tempfile.TemporaryDirectory(prefix="hiddenjax-mitsuba-") as tmp:
        integrator = {"type": "path", "max_depth": int(max_depth)}
        mscene = mi.load_dict({**_scene_dict(mi, scene, camera, Path(tmp), integrator),
                               "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(pano))}})
        return np.array(mi.render(mscene, spp=spp, seed=seed), dtype=np.float32)
