"""Light fitting on path-traced photos: accuracy from near and far starts, time per light.

    python benchmarks/bench_light_fit.py [--quick] [--out DIR] [--part all|single|multi|textured|faulty]
                                         [--cases N] [--seed S] [--table plain|wood|satin] [--plate]
                                         [--told-gloss ROUGHNESS]

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

`--part faulty` (not part of `all`): real-photo faults on a desk (a 0.9 x 0.7 m plane of albedo
0.6) with a pencil (a cylinder 8 mm across, 76 mm tall) and, in every third case, a cup (a
cylinder 8 cm across, 9 cm tall) beside it, under one lamp (two in every fourth case) at 0.3-1 m
from the pencil, 35-65 degrees above the desk, on the far side so the shadows fall towards the
camera (160 x 120 pixels, 60 degree field of view, 0.44 m away). Each photo is path-traced, then
vignetted (`1 - 0.35 r^2`, `r` over the half-diagonal), scaled to its 99.5th percentile,
clipped and encoded with an unknown gamma drawn in [1.8, 2.4]; the scene the fit is given has
every object 3 mm from its true place (a random horizontal direction). Fits as `hiddenjax lights`
does without a reference: `fit_lights(clearance=0.005, shading="smooth")` in a box of +-1.1 m
around the pencil, no start, no mask. Reported per light: the angle between the found and the
true direction from the occluders' centre, the position error, the distance error, and whether
the truth lies inside the reported 95% cone and interval (`light_uncertainty`), each on its own,
with the distance error in standard deviations, and the falloff fit's own signs (its shadow
prior's widening, the residual's correlation area and noise, the tone curve's power) and whether a
warning names it or the whole fit (the summary counts the lights warned of, and those outside
their region with no warning); beside it the plain fit (`fit_lights` with neither) on the same
photos. `--seed` draws other desks (lamps, objects' errors, gammas). `--table wood` puts the desks
on a matte wood grain (2 cm stripes, albedo 0.4-0.8 around 0.6), `--table satin` under a glossy
layer (GGX roughness 0.25, index 1.5); the fit is told the plain desk (with `--told-gloss 0.4`,
a glossy desk of a guessed roughness, as a scene file's `roughness = 0.4` declares it, which the
fit refines), and the same seed draws the same lamps, errors and gammas on every table. `--plate`
adds a third fit from each photo and its clean plate (the desk without the objects, through the
same camera faults): `fit_lights(clearance=0.005, shading="smooth", reference=plate)`, as
`hiddenjax lights --reference` does.
"""

import argparse
import itertools
import json
import time
import warnings
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


def _seen(u, light):
    """`(angle, distance, coverage)` of the true `light` against one row `u` of `light_uncertainty`: the
    angle between the found and true directions from the objects, the true distance, and `_coverage`."""
    true = light - u["anchor"]
    distance = float(np.linalg.norm(true))
    angle = float(np.degrees(np.arccos(np.clip(u["direction"] @ true / distance, -1, 1))))
    return angle, distance, _coverage(u, angle, distance)


def _coverage(u, angle, distance) -> dict:
    """Whether the truth lies in the 95% cone and distance interval of one row `u` of
    `light_uncertainty` (`inside`), in each on its own, and the distance error in standard deviations
    (`sigma`); without a covariance not inside, the rest None."""
    if u["angle"] is None:
        return dict(inside=False, inside_cone=None, inside_interval=None, distance_z=None)
    cone, interval = bool(angle <= u["angle"]), bool(u["interval"][0] <= distance <= u["interval"][1])
    return dict(inside=cone and interval, inside_cone=cone, inside_interval=interval,
                distance_z=float((u["distance"] - distance) / u["sigma"]))


def _inside(fit, scene, light) -> bool:
    return _seen(hj.shadows.light_uncertainty(fit, scene)[0], light)[2]["inside"]


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


DESK = (0.9, 0.7)
PENCIL = ("cylinder", dict(radius=0.004, height=0.076), (0.0, 0.0, 0.0))
CUP = ("cylinder", dict(radius=0.04, height=0.09), (0.1, 0.0, 0.06))


def desk_scene(objects, offset=(0.0, 0.0, 0.0), table=0.6, roughness=None):
    """The desk (albedo `table`, a constant or a texture; glossy with a `roughness`) and its objects
    (`(shape, sizes, place)`), each moved by `offset` metres."""
    surfaces = [hj.Surface(hj.scene.primitive("plane", extent=DESK), table, roughness=roughness)]
    for shape, sizes, place in objects:
        mesh = hj.scene.primitive(shape, **sizes)
        mesh.apply_translation(np.asarray(place) + np.asarray(offset))
        surfaces.append(hj.Surface(mesh, 0.5, observe=False))
    return hj.Scene(surfaces)


def faulty_photo(photo, rng, plate=None):
    """Vignetting, a white point at the 99.5th percentile (clipped above) and an unknown gamma: `(photo, gamma)`,
    and with a `plate` (the same view without the objects) `(photo, gamma, plate)`, the plate taken with the
    same camera (the same vignetting, exposure and tone curve)."""
    H, W = photo.shape[:2]
    rows, cols = np.mgrid[:H, :W] + 0.5
    r2 = ((rows - H / 2) ** 2 + (cols - W / 2) ** 2) / ((H / 2) ** 2 + (W / 2) ** 2)
    gamma, white = rng.uniform(1.8, 2.4), np.percentile(photo, 99.5)
    camera = lambda radiance: np.clip(radiance * (1 - 0.35 * r2) / white, 0, 1) ** (1 / gamma)
    return (camera(photo), gamma) if plate is None else (camera(photo), gamma, camera(plate))


def _falloff_signs(falloff, k: int) -> dict:
    """What the falloff fit says of its own health for light `k` (none without it): how many times the
    shadow's direction prior was widened, the residual's correlation area (pixels) before the prior's
    check and after the last fit (`misfit`, which the fit's warning reads), its noise (log radiance),
    the tone curve's power, the ambient over the lamps' mean radiance (the desks have none) and a glossy
    desk's fitted roughness (None: matte)."""
    if falloff is None:
        return {}
    return dict(prior_scale=float(falloff.prior_scale[k]), correlation=falloff.correlation, misfit=falloff.misfit,
                noise=falloff.noise, tone_power=falloff.beta, ambient=falloff.ambient, roughness=falloff.roughness)


def _warned(notes, k: int) -> bool:
    """Whether a warning names light `k` or the whole fit (one that names no light)."""
    return any(note.startswith((f"light {k} ", f"light {k}:")) or not note.startswith("light ") for note in notes)


def desk_table(name: str):
    """`desk_scene`'s `(table, roughness)` for a table kind: `plain` (albedo 0.6), `wood` (matte grain,
    `hj.scenes.wood_texture` with 2 cm stripes over the desk's 0.9 m, stretched to albedo 0.4-0.8,
    median 0.6) or `satin` (albedo 0.6 under a GGX layer of roughness 0.25, index 1.5)."""
    if name == "wood":
        t = hj.scenes.wood_texture(DESK[0], 1024, grain=0.02, mean=0.5, seed=3)
        lo, hi = np.percentile(t, [1, 99])
        return np.clip(0.4 + 0.4 * (t - lo) / (hi - lo), 0.35, 0.85), None
    return 0.6, (0.25 if name == "satin" else None)


def _faulty(cases, render, table, rng, desk="plain", plate=False, told=None):
    """The faulty-photo study (module docstring) on a `desk` table: one row per light and fit; with a
    `plate`, a third fit from the photo and its clean plate (`fit_lights(shading="smooth", reference=)`);
    `told`: the fit's desk is glossy, of that roughness (a satin table declared in the scene file; the fit
    takes it as a start and fits it)."""
    cam = hj.Camera.look_at([0.0, 0.32, 0.30], [0.0, 0.0, -0.02], [0, 1, 0], 60.0, 160, 120)
    box = np.array([[-1.1, 0.1, -1.1], [1.1, 1.1, 1.1]])
    rows = []
    table_kind = desk_table(desk)  # (the wood texture drawn once, not per case)
    for case in range(cases):
        objects = [PENCIL, CUP] if case % 3 == 2 else [PENCIL]
        count = 2 if case % 4 == 3 else 1
        anchor = np.array([0.0, 0.038, 0.0])
        lights = []
        for _ in range(count):
            distance, elevation = rng.uniform(0.3, 1.0), np.radians(rng.uniform(35, 65))
            azimuth = np.pi + rng.uniform(-0.5, 0.5) * np.pi
            lights.append(anchor + distance * np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                                                        np.cos(elevation) * np.cos(azimuth)]))
        lights = np.array(lights)
        empty = render(desk_scene([], (0.0, 0.0, 0.0), *table_kind), cam, lights) if plate else None
        photo, gamma, *taken = faulty_photo(render(desk_scene(objects, (0.0, 0.0, 0.0), *table_kind), cam, lights),
                                            rng, empty)
        offset = rng.normal(size=3) * np.array([1.0, 0.0, 1.0])
        model = desk_scene(objects, 0.003 * offset / np.linalg.norm(offset), 0.6, told or None)
        fits = [("clearance + smooth shading", photo, dict(clearance=0.005, shading="smooth")), ("plain", photo, {})]
        if plate:
            fits.append(("clearance + smooth shading + clean plate", photo,
                         dict(clearance=0.005, shading="smooth", reference=taken[0])))
        for label, image, options in fits:
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit = hj.shadows.fit_lights(image, model, cam, None, count=count, box=box, **options)
            seconds = time.perf_counter() - t
            found = hj.shadows.light_uncertainty(fit, model)
            order = min(itertools.permutations(range(count)),
                        key=lambda p: np.sum(np.linalg.norm(fit.positions[list(p)] - lights, axis=1)))
            for light, k in zip(lights, order):
                u = found[k]
                angle, true_distance, coverage = _seen(u, light)
                rows.append(dict(case=case, fit=label, objects=len(objects), lights=count, gamma=gamma,
                                 light=light.tolist(), distance_m=true_distance, direction_error_deg=angle,
                                 position_error_m=float(np.linalg.norm(fit.positions[k] - light)),
                                 distance_error_m=u["distance"] - true_distance,
                                 cone_deg=u["angle"], interval_m=None if u["interval"] is None else u["interval"].tolist(),
                                 **coverage, seconds=seconds,
                                 warnings=list(fit.warnings), warned=_warned(fit.warnings, k),
                                 **_falloff_signs(fit.falloff, k)))
                table.append((f"case {case}: {len(objects)} object(s), {count} lamp(s), {true_distance:.2f} m, "
                              f"gamma {gamma:.2f}", label, f"{angle:.2f} deg / {100 * rows[-1]['position_error_m']:.1f} cm",
                              f"{seconds:.0f}" + (", inside 95%" if coverage["inside"] else "")))
    return rows


def _faulty_summary(rows) -> dict:
    out = {}
    for label in sorted({r["fit"] for r in rows}):
        mine = [r for r in rows if r["fit"] == label]
        direction = np.array([r["direction_error_deg"] for r in mine])
        position = np.array([r["position_error_m"] / r["distance_m"] * 0.5 for r in mine])  # at 0.5 m
        out[label] = dict(lights=len(mine), direction_median_deg=float(np.median(direction)),
                          direction_within_3deg=float(np.mean(direction <= 3)),
                          position_at_half_metre_median_m=float(np.median(position)),
                          position_within_5cm_at_half_metre=float(np.mean(position <= 0.05)),
                          inside_95=float(np.mean([r["inside"] for r in mine])),
                          warned=int(sum(r["warned"] for r in mine)),
                          outside_unwarned=int(sum(not r["inside"] and not r["warned"] for r in mine)),
                          **_calibration(mine),
                          seconds_median=float(np.median([r["seconds"] for r in mine])))
    return out


def _calibration(rows) -> dict:
    """The share of lights inside the 95% cone and inside the 95% interval, and the mean and RMS of
    the distance errors in standard deviations (0 and 1 for calibrated intervals)."""
    rows = [r for r in rows if r["distance_z"] is not None]
    if not rows:
        return {}
    z = np.array([r["distance_z"] for r in rows])
    return dict(inside_cone=float(np.mean([r["inside_cone"] for r in rows])),
                inside_interval=float(np.mean([r["inside_interval"] for r in rows])),
                distance_z_mean=float(z.mean()), distance_z_rms=float(np.sqrt(np.mean(z**2))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench_light_fit"))
    ap.add_argument("--part", choices=("all", "single", "multi", "textured", "faulty"), default="all",
                    help="single lights, several at once, both (the starts are the same either way), a "
                         "textured table with a reference photo, or faulty desk photos (not in all)")
    ap.add_argument("--cases", type=int, default=16, help="faulty desk photos (--part faulty; default 16)")
    ap.add_argument("--table", choices=("plain", "wood", "satin"), default="plain",
                    help="the faulty desks' table (--part faulty): matte plain (default), matte wood grain or "
                         "glossy satin; the fit is told only the plain desk unless --told-gloss")
    ap.add_argument("--told-gloss", type=float, default=None, metavar="ROUGHNESS",
                    help="--table satin: the fit's desk is glossy (index 1.5), of this roughness as a scene file "
                         "would declare it (roughness = 0.4: a guess; the satin's is 0.25), which the fit refines")
    ap.add_argument("--plate", action="store_true",
                    help="--part faulty: a third fit from each photo and its clean plate (the desk without the "
                         "objects, the same camera): hiddenjax lights --reference")
    ap.add_argument("--seed", type=int, default=7,
                    help="the faulty photos' draws (--part faulty; default 7): another seed, other desks")
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
    if args.part == "faulty":
        if args.told_gloss is not None and args.table != "satin":
            ap.error("--told-gloss declares the satin table's layer: use it with --table satin")
        if args.told_gloss is not None:
            try:
                hj.scene._gloss.check_gloss(args.told_gloss, 1.5)
            except ValueError as e:
                ap.error(f"--told-gloss: {e}")
        rows = _faulty(2 if args.quick else args.cases, render, table, np.random.default_rng(args.seed), args.table,
                       args.plate, args.told_gloss)
        results = dict(photos=photos, seed=args.seed, table=args.table, told_gloss=args.told_gloss, faulty=rows,
                       summary=_faulty_summary(rows))
        table.print_all()
        for label, summary in results["summary"].items():
            print(f"{label}: direction within 3 deg {summary['direction_within_3deg']:.0%} (median "
                  f"{summary['direction_median_deg']:.2f}), position within 5 cm at 0.5 m "
                  f"{summary['position_within_5cm_at_half_metre']:.0%}, truth inside the 95% cone and interval "
                  f"{summary['inside_95']:.0%}, {summary['seconds_median']:.0f} s per fit")
            if "inside_cone" in summary:
                print(f"  inside the cone {summary['inside_cone']:.0%}, inside the interval "
                      f"{summary['inside_interval']:.0%}; distance error in standard deviations: mean "
                      f"{summary['distance_z_mean']:.2f}, RMS {summary['distance_z_rms']:.2f}")
        _faulty_picture(args.out / "faulty.png", rows)
        (args.out / "results.json").write_text(json.dumps(results, indent=2))
        return
    for name in fixtures if args.part not in ("textured",) else []:
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
                                              ambient=fit.ambient, inside_95=_inside(fit, scene, light)))
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


def _faulty_picture(path, rows):
    """Direction error against distance error per light, each fit its marker; the 95% cone as bars."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for label, marker in (("clearance + smooth shading", "o"), ("plain", "x"), ("clearance + smooth shading + clean plate", "s")):
        mine = [r for r in rows if r["fit"] == label]
        if not mine:
            continue
        ax.scatter([100 * r["distance_error_m"] for r in mine], [r["direction_error_deg"] for r in mine],
                   marker=marker, label=label)
    ax.axhline(3.0, color="k", ls="--", lw=0.8)
    finish_plot(fig, ax, path, "distance error (cm, found - true)", "direction error (deg)",
                "faulty desk photos: vignetting, unknown gamma,\nobjects 3 mm off")


if __name__ == "__main__":
    main()
