"""A ball as a light probe under real skies: `hj.photo.Probe` on photos from the reference renderer.

A matte ball (albedo 0.8) stands alone under a real HDR panorama, seen by a distant camera; its photo
comes from `hj.reference_render` (Embree, 64 directions per map cell of the full panorama, 4
samples per pixel: a path apart from the probe's transport matrix). The probe fits the sphere
to its mask, builds one matrix for the view and gives each sky's map and dominant lights. The
figures: the brightest light's angle to the panorama's brightest source, "the sun" (the first
moment of its pixels within 3 degrees of the brightest one; lebombo's is a sunny window) and the tone-mapped SSIM against the panorama of
the map that the default prior solves from the probe's matrix (the probe's own map, under a weak
prior, is only the lights' start). A ball sees only the half of the sky that faces the camera, so the map's
other half is the prior's guess. Each sky also reports whether the probe fitted a highlight (it should not:
the ball is matte) and the brightest light of the diffuse model alone (`gloss=False`).

    python examples/light_probe.py [--quick] [--out DIR]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import hiddenjax as hj

ROOT = Path(__file__).resolve().parents[1]
SKIES = ("immenstadter_horn", "lebombo", "adams_place_bridge")


def sun_direction(panorama) -> np.ndarray:
    """The panorama's sun: the first moment of its pixels within 3 degrees of the brightest one."""
    grey = panorama.mean(axis=-1) if panorama.ndim == 3 else panorama
    H, W = grey.shape
    fine = hj.EnvGrid(H, W)
    d = np.asarray(fine.directions()).reshape(-1, 3)
    peak = d[np.argmax(grey)]
    near = d @ peak > np.cos(np.radians(3))
    m = (grey.reshape(-1)[near, None] * d[near]).sum(axis=0)
    return m / np.linalg.norm(m)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one sky, a 47-pixel ball (94 without)")
    parser.add_argument("--out", type=Path, default=Path("light_probe_out"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    skies = SKIES[:1] if args.quick else SKIES
    size = 56 if args.quick else 112
    radius_px = 0.42 * size
    # The ball (radius 1) photographed from 100 radii along +z (the disc centred, 0.3 degrees from orthographic);
    # the probe models it from 1000. Farther, float32 hit points stray past the renderer's shadow-ray offset.
    focal = radius_px * np.sqrt(100.0**2 - 1)
    camera = hj.Camera.from_opencv(np.array([[focal, 0, size / 2 - 0.5], [0, focal, size / 2 - 0.5], [0, 0, 1]]),
                                   np.diag([1.0, -1.0, -1.0]), [0, 0, 100.0], size, size)
    rr, cc = np.mgrid[:size, :size] + 0.5
    mask = (rr - size / 2) ** 2 + (cc - size / 2) ** 2 <= radius_px**2  # what a user paints
    import trimesh

    # rendered flat-shaded (20480 facets of 1.3 degrees): the renderer traces every shadow ray, and a smooth
    # normal would send some into the ball's own facets
    ball = hj.Scene([hj.Surface(trimesh.creation.icosphere(subdivisions=5), 0.8)])
    grid = hj.EnvGrid(32, 64)
    rows = []
    sheet = []
    for sky in skies:
        panorama = hj.io.read_hdr(ROOT / "data_fixtures" / "hdri" / f"{sky}.hdr")
        t0 = time.perf_counter()
        photo = hj.reference_render(ball, camera, panorama, samples=64, pixel_samples=4)
        render = time.perf_counter() - t0
        t0 = time.perf_counter()
        probe = hj.photo.Probe.sphere(mask)
        found = probe.solve(photo)
        seconds = time.perf_counter() - t0
        diffuse = probe.solve(photo, gloss=False)  # the diffuse model alone (probe --matte)
        sun = sun_direction(panorama)
        error = float(np.degrees(np.arccos(np.clip(np.asarray(found.lights.directions[0]) @ sun, -1, 1))))
        matte = float(np.degrees(np.arccos(np.clip(np.asarray(diffuse.lights.directions[0]) @ sun, -1, 1))))
        truth = grid.downsample(panorama)
        env = np.asarray(hj.solve_illumination(probe.T, probe.averaged(photo)).env)
        ssim = float(hj.metrics.env_errors(env.mean(-1) if env.ndim == 3 else env,
                                           truth.mean(-1) if truth.ndim == 3 else truth, region="all")["ssim_tm"])
        facing = float(sun[2])
        rows.append(dict(sky=sky, sun_error_deg=error, sun_facing_camera=facing, ssim_tm_all=ssim,
                         lights=len(found.lights), probe_seconds=seconds, render_seconds=render,
                         highlight=None if found.lobe is None else [found.lobe.weight, found.lobe.roughness],
                         matte_sun_error_deg=matte))
        print(f"{sky}: the brightest light {error:.2f} deg from the sun (sun's z {facing:+.2f}: "
              f"{'facing' if facing > 0 else 'behind'} the camera's side), {len(found.lights)} light(s), map "
              f"tone-mapped SSIM {ssim:.3f} (default prior); probe {seconds:.1f} s; {found.lobe or 'no highlight'} "
              f"(the diffuse model alone: {matte:.2f} deg)", flush=True)
        sheet += [(f"{sky}\nsun {error:.1f} deg off", photo), ("map, default prior\n", env), ("panorama on the grid\n", truth)]
    hj.io.contact_sheet(args.out / "light_probe.png", sheet, height=160, columns=3)
    (args.out / "results.json").write_text(json.dumps(dict(skies=rows, grid=[32, 64], quick=args.quick), indent=2))
    print(f"wrote {args.out}/light_probe.png and results.json")


if __name__ == "__main__":
    main()
