"""Light fitting on path-traced photos: accuracy from near and far starts, time per light.

    python benchmarks/bench_light_fit.py [--quick] [--out DIR] [--part all|single|multi|textured]

Photos: Mitsuba 3's path tracer (`max_depth=4`: direct light plus two diffuse bounces, 256 spp,
box filter) of the fixtures on a table at 128x128 pixels, each under one isotropic point light
(0.05 W/sr) at three positions, and under several lights at once (the teapot and the coded
aperture under three, the sphere under two). Without Mitsuba the
photos fall back to Embree hard-shadow renders plus a constant ambient (reported in
`results.json` as `photos`). Fits: `hj.shadows.fit_lights` from a start 5 cm and 30 cm off (a
random direction) and with no start at all (`init=None`: the global search in the default box),
with their defaults: the ambient term, the search, then the polish (box-filtered Embree shadows
plus two bounces; joint Levenberg-Marquardt, then Nelder-Mead). Baseline in the same run: one
Embree hard-shadow render of the same image (`hj.render_point_lights`).

`--part textured`: the teapot on a wood-textured table (`hj.scenes.wood_texture`, mean albedo
0.5) under the three single lights, photographed with and without the teapot (the reference);
fits with `reference=` from 5 cm, 30 cm and no start, and without it from 5 cm, on a scene that
knows only the table's mean albedo.
"""

import argparse
import itertools
import json
import time
from pathlib import Path

import matplotlib
import numpy as np

import hiddenjax as hj
from _report import Table, finish_plot  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

INTENSITY = 0.05
LIGHTS = np.array([[0.12, 0.35, 0.08], [-0.2, 0.25, 0.1], [0.05, 0.45, -0.18]])


def photo_renderer():
    """Mitsuba's path tracer when it is installed, else Embree hard shadows plus an ambient."""
    try:
        from hiddenjax.transport._mitsuba import render_point_lights_mitsuba

        render_point_lights_mitsuba(*_fixture("sphere", 8), LIGHTS[:1], [INTENSITY], spp=1)
        return "mitsuba path tracer, max_depth=4, 256 spp", lambda scene, cam, lights: render_point_lights_mitsuba(
            scene, cam, lights, [INTENSITY] * len(lights), max_depth=4, spp=256)
    except ImportError:
        def fallback(scene, cam, lights):
            image = hj.render_point_lights(scene, cam, lights, [INTENSITY] * len(lights))
            return image + 0.1 * image.mean()

        return "embree hard shadows + 10% ambient (mitsuba not installed)", fallback


def _fixture(name, size):
    setup = hj.scenes.object_on_plane(name, width=size, height=size)
    return setup.scene, setup.camera


def _embree_seconds(scene, cam, lights):
    """Best of three Embree hard-shadow renders of the photo (`pixel_samples=1`, the search's rays)."""
    times = []
    for _ in range(3):
        t = time.perf_counter()
        hj.render_point_lights(scene, cam, lights, [INTENSITY] * len(lights), pixel_samples=1)
        times.append(time.perf_counter() - t)
    return min(times)


def _error(found, truth):
    """Per-light distances (m) under the best matching of found to true lights."""
    best = min(itertools.permutations(range(len(truth))),
               key=lambda p: np.sum(np.linalg.norm(found[list(p)] - truth, axis=1)))
    return np.linalg.norm(found[list(best)] - truth, axis=1)


def _textured(size, lights, render, table):
    """The teapot on a wood-textured table: fits with and without a reference photo."""
    plain = hj.scenes.object_on_plane("teapot", width=size, height=size, plane_albedo=0.5)  # what the fit knows
    span = float(np.ptp(plain.scene[0].mesh.vertices[:, 0]))
    texture = hj.scenes.wood_texture(span)
    textured = hj.scenes.object_on_plane("teapot", width=size, height=size, plane_albedo=texture)
    table_alone = hj.Scene([textured.scene[0]])
    rng, rows = np.random.default_rng(1), []
    for light in lights:
        photo = render(textured.scene, textured.camera, light[None])
        reference = render(table_alone, textured.camera, light[None])
        for start, with_reference in ((0.05, True), (0.30, True), (None, True), (0.05, False)):
            d = rng.normal(size=3)
            init = None if start is None else light[None] + start * d / np.linalg.norm(d)
            t = time.perf_counter()
            fit = hj.shadows.fit_lights(photo, plain.scene, plain.camera, init,
                                        reference=reference if with_reference else None)
            seconds = time.perf_counter() - t
            err = float(np.linalg.norm(fit.positions[0] - light))
            rows.append(dict(light=light.tolist(), start=start, reference=with_reference, error_m=err,
                             seconds=seconds, intensity=float(fit.intensities[0])))
            table.append((f"teapot, textured table {light.tolist()}",
                          ("none" if start is None else f"{100 * start:.0f} cm off")
                          + (", reference" if with_reference else ", no reference"),
                          f"{100 * err:.2f}", f"{seconds:.1f}"))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench_light_fit"))
    ap.add_argument("--part", choices=("all", "single", "multi", "textured"), default="all",
                    help="single lights, several at once, both (the starts are the same either way), or a "
                         "textured table with a reference photo")
    args = ap.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, fixtures, lights = (48, ["sphere"], LIGHTS[:1]) if args.quick else (128, ["teapot", "sphere", "coded_aperture"],
                                                                               LIGHTS)
    photos, render = photo_renderer()
    rng = np.random.default_rng(0)
    results = dict(photos=photos, size=size, intensity=INTENSITY, single=[], multi=None)
    table = Table()
    table.append(("fixture / light", "start", "error (cm)", "time (s), x Embree render"))
    for name in fixtures if args.part != "textured" else []:
        scene, cam = _fixture(name, size)
        for light in lights:
            if args.part == "multi":  # draw the same starts, fit nothing
                rng.normal(size=(2, 3))
                continue
            photo = render(scene, cam, light[None])
            embree = _embree_seconds(scene, cam, light[None])
            for start in (0.05, 0.30, None):
                if start is None:
                    init = None
                else:
                    d = rng.normal(size=3)
                    init = light[None] + start * d / np.linalg.norm(d)
                t = time.perf_counter()
                fit = hj.shadows.fit_lights(photo, scene, cam, init)
                seconds = time.perf_counter() - t
                err = float(np.linalg.norm(fit.positions[0] - light))
                label = "none" if start is None else f"{100 * start:.0f} cm off"
                results["single"].append(dict(fixture=name, triangles=len(scene[1].triangles), light=light.tolist(),
                                              start=start, error_m=err, seconds=seconds, embree_s=embree,
                                              ambient=fit.ambient))
                table.append((f"{name} ({len(scene[1].triangles)} tri) {light.tolist()}", label, f"{100 * err:.2f}",
                              f"{seconds:.1f}, {seconds / embree:.0f}x"))
    if not args.quick and args.part in ("all", "multi"):
        for name, count in (("teapot", 3), ("sphere", 2), ("coded_aperture", 3)):
            scene, cam = _fixture(name, size)
            truth = LIGHTS[:count]
            photo = render(scene, cam, truth)
            for start in (0.30, None):
                init = None if start is None else truth + start * rng.normal(size=(count, 3)) / np.sqrt(3)
                t = time.perf_counter()
                fit = hj.shadows.fit_lights(photo, scene, cam, init, count=count)
                seconds = time.perf_counter() - t
                err = _error(fit.positions, truth)
                results["multi"] = (results["multi"] or []) + [dict(fixture=name, lights=count, start=start,
                                                                    errors_m=err.tolist(), seconds=seconds)]
                table.append((f"{name}, {count} lights", "none" if start is None else "~30 cm off",
                              " / ".join(f"{100 * e:.2f}" for e in err),
                              f"{seconds:.1f} ({seconds / count:.1f} per light)"))
    if args.part in ("all", "textured"):
        results["textured"] = _textured(size, lights, render, table)
    table.print_all()

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for start, marker in ((0.05, "o"), (0.30, "s"), (None, "^")):
        rows = [r for r in results["single"] if r["start"] == start]
        ax.scatter([r["seconds"] for r in rows], [100 * r["error_m"] for r in rows], marker=marker,
                   label="no start" if start is None else f"start {100 * start:.0f} cm off")
    ax.axhline(1.0, color="k", ls="--", lw=0.8)
    finish_plot(fig, ax, args.out / "light_fit.png", "seconds per light", "error (cm)", f"{photos}, {size}x{size}")
    (args.out / "results.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
