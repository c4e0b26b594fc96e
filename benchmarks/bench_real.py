"""Real photographs of an object: `probe` on the DiLiGenT ball, one light and two at once.

    python benchmarks/bench_real.py [--quick] [--out DIR] [--diligent DIR] [--pairs N] [--measured-pairs N]

`--diligent DIR`: the DiLiGenT "ball" (Shi et al., CVPR 2016; research use, not shipped): a real,
somewhat shiny sphere photographed 96 times, each under one calibrated distant light (16-bit linear
PNGs `001.png` .. `096.png`, `mask.png`, `light_directions.txt` in the camera frame x right, y up,
z towards the camera, `filenames.txt`). Get it from the DiLiGenT site (`pmsData/ballPNG`) and crop
nothing: the probe fits the sphere to the mask. Each photo alone goes through `hj.photo.Probe`
(the build once, then each photo's map, its dominant lights and their refinement, the ball's
highlight fitted with them where it explains the photo far better: the probe's default), and the figure
is the angle between the brightest light found and the calibrated one; then `--pairs` random
pairs of photos whose lights are at least 30 degrees apart are summed (the photos are linear: two
lights at once) and both lights must be found. The baseline in the same run is a plain Lambertian
least-squares fit on the mask's normals (`b = argmin ||N b - y||` over the unsaturated pixels
brighter than 10% of the sphere's 95th percentile, not of its maximum, which is a highlight; the
light is `b / |b|`). For the pairs, the ceiling of that model in the same run: the two-light
Lambertian fit `y = p1 max(0, n.l1) + p2 max(0, n.l2)` started at the calibrated directions (and
each photo's own 95th percentile as power), with the pixels far darker than the fit (the
terminators' misfit, not highlights) left out over three passes: what a diffuse model can say
about two lights on this ball at all.

Then the same photos through the probe with the ball's BRDF measured from its own other photos
(`hj.photo.measure_reflectance` with the calibrated directions and intensities; `probe
--measure-reflectance`), never from the photos being solved: each photo alone with the table of
the three of four folds it is not in, each of the first `--measured-pairs` pairs (default all) with
the table of the other 94 photos.

Without `--diligent` (and in `--quick`), the same measurements run on closed-form photos of a
Lambertian sphere (analytic normals, 4x4 samples per pixel, 0.5% noise) so the script always
measures something. `--quick`: 12 photos, 5 pairs. Writes `results.json` and `probe.png` (photos,
maps with the lights found and the truth).
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import hiddenjax as hj
from _report import Table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(unit(a) @ unit(b), -1, 1))))


def load_diligent(folder: Path):
    """`(mask, photos (M, H, W, 3), saturated (M, H, W), lights (M, 3), powers (M, 3))` of the DiLiGenT ball
    folder (`powers`: the calibrated light intensities per channel)."""
    names = (folder / "filenames.txt").read_text().split()
    lights = unit(np.loadtxt(folder / "light_directions.txt"))
    mask = hj.io.read_image(folder / "mask.png")
    mask = (mask.mean(axis=-1) if mask.ndim == 3 else mask) > 0.5
    shots = [hj.photo.read_photo(folder / n) for n in names]
    powers = np.loadtxt(folder / "light_intensities.txt")
    return mask, np.stack([s.radiance for s in shots]), np.stack([s.saturated for s in shots]), lights, powers


def synthetic(count: int, seed: int = 0):
    """Closed-form Lambertian sphere photos under one light each (the same layout as `load_diligent`)."""
    rng = np.random.default_rng(seed)
    size, centre, radius, ss = (120, 130), (58.6, 66.2), 50.3, 4
    u = (np.arange(ss) + 0.5) / ss
    rows = (np.arange(size[0])[:, None] + u).reshape(-1)
    cols = (np.arange(size[1])[:, None] + u).reshape(-1)
    x, y = (cols[None, :] - centre[1]) / radius, -(rows[:, None] - centre[0]) / radius
    inside = x**2 + y**2 < 1
    n = np.stack([x + 0 * y, y + 0 * x, np.sqrt(np.maximum(0, 1 - x**2 - y**2))], -1)
    lights = unit(np.column_stack([rng.uniform(-0.6, 0.6, count), rng.uniform(-0.6, 0.6, count), np.ones(count)]))
    photos = []
    for w in lights:
        image = (np.maximum(0, n @ w) / np.pi * inside).reshape(size[0], ss, size[1], ss).mean(axis=(1, 3))
        image = image * (1 + 0.005 * rng.normal(size=image.shape))
        photos.append(np.repeat(image[..., None], 3, axis=2).astype(np.float32))
    rr, cc = np.mgrid[: size[0], : size[1]] + 0.5
    mask = (rr - centre[0]) ** 2 + (cc - centre[1]) ** 2 <= radius**2
    return mask, np.stack(photos), np.zeros((count,) + size, bool), lights, np.ones((count, 3))


def sphere_pixels(mask, photo, saturated):
    """`(normals (N, 3), grey (N,), unsaturated (N,))` at the mask's pixels inside its fitted sphere."""
    pixels, n, _ = hj.photo.sphere_normals(mask)
    rr, cc = pixels.T
    return n, photo.mean(axis=-1)[rr, cc], ~saturated[rr, cc]


def lambertian_fit(mask, photo, saturated) -> np.ndarray:
    """The baseline: least squares `N b = y` on the mask's sphere normals (module docstring)."""
    n, grey, unsaturated = sphere_pixels(mask, photo, saturated)
    good = (grey > 0.1 * np.percentile(grey, 95)) & unsaturated  # not of the max: a highlight
    b, *_ = np.linalg.lstsq(n[good], grey[good], rcond=None)
    return unit(b)


def two_light_ceiling(mask, photo, saturated, starts, powers) -> np.ndarray:
    """The two-light Lambertian fit started at the truth (module docstring): `(2, 3)` directions."""
    from scipy.optimize import least_squares

    n, grey, good = sphere_pixels(mask, photo, saturated)

    def directions(p):
        theta, phi = p[0::3], p[1::3]
        return np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])

    def render(p, normals):
        return np.maximum(0, normals @ directions(p).T) @ np.exp(p[2::3])

    p = np.concatenate([[np.arccos(s[2]), np.arctan2(s[1], s[0]), np.log(w)] for s, w in zip(unit(starts), powers)])
    used = good
    for _ in range(3):
        p = least_squares(lambda q: render(q, n[used]) - grey[used], p, method="lm").x
        residual = render(p, n) - grey
        used = good & (residual > -3 * 1.4826 * np.median(np.abs(residual[used])))
    return directions(p)


def worse_of_two(found, truth) -> float:
    """The worse angular error of two found lights against two true ones, matched the better way."""
    if len(found) < 2:
        return 180.0
    return min(max(angle(found[0], truth[0]), angle(found[1], truth[1])),
               max(angle(found[0], truth[1]), angle(found[1], truth[0])))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="12 photos, 5 pairs")
    parser.add_argument("--out", type=Path, default=Path("bench_real_out"))
    parser.add_argument("--diligent", type=Path, help="the DiLiGenT ball folder (research use; not shipped)")
    parser.add_argument("--pairs", type=int, default=50, help="random pairs of photos summed (default 50)")
    parser.add_argument("--measured-pairs", type=int, help="of those, the first N with the measured BRDF (default all)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.diligent is not None and not (args.diligent / "light_directions.txt").is_file():
        parser.error(f"{args.diligent} is not the DiLiGenT ball folder (no light_directions.txt)")
    source = "diligent" if args.diligent is not None else "closed-form sphere"
    mask, photos, saturated, lights, light_powers = load_diligent(args.diligent) if args.diligent else synthetic(96)
    singles = np.arange(len(photos)) if not args.quick else np.linspace(0, len(photos) - 1, 12).round().astype(int)
    pairs = 5 if args.quick else args.pairs
    print(f"{source}: {len(singles)} photos alone, {pairs} pairs; the sphere is "
          f"{2 * hj.photo.fit_sphere(mask)[2]:.0f} pixels across")

    t0 = time.perf_counter()
    probe = hj.photo.Probe.sphere(mask)
    build = time.perf_counter() - t0
    table = Table()
    table.append(("photo", "probe (deg)", "Lambertian fit (deg)", "lights found", "highlight", "seconds"))
    single, baseline, seconds, maps, highlights = [], [], [], [], []
    for k in singles:
        t1 = time.perf_counter()
        found = probe.solve(photos[k], saturated[k])
        seconds.append(time.perf_counter() - t1)
        single.append(angle(found.lights.directions[0], lights[k]))
        baseline.append(angle(lambertian_fit(mask, photos[k], saturated[k]), lights[k]))
        maps.append((k, found))
        highlights.append(found.lobe is not None)
        table.append((f"{k + 1:03d}", f"{single[-1]:.2f}", f"{baseline[-1]:.2f}", str(len(found.lights)),
                      str(found.lobe or "-"), f"{seconds[-1]:.2f}"))

    rng = np.random.default_rng(0)
    pair_rows, both, ceiling = [], [], []
    while len(pair_rows) < pairs:
        a, b = rng.choice(len(photos), 2, replace=False)
        if angle(lights[a], lights[b]) < 30:
            continue
        result = probe.solve(photos[a] + photos[b], saturated[a] | saturated[b])
        d = np.asarray(result.lights.directions)
        worst = worse_of_two(d, lights[[a, b]])
        powers = [np.percentile(photos[k].mean(axis=-1)[mask], 95) for k in (a, b)]
        best = worse_of_two(two_light_ceiling(mask, photos[a] + photos[b], saturated[a] | saturated[b],
                                              lights[[a, b]], powers), lights[[a, b]])
        both.append(worst)
        ceiling.append(best)
        pair_rows.append(dict(photos=[int(a) + 1, int(b) + 1], separation=angle(lights[a], lights[b]),
                              lights_found=len(d), worse_error=worst, ceiling_worse_error=best,
                              highlight=None if result.lobe is None else [result.lobe.weight, result.lobe.roughness]))
        print(f"pair {a + 1:03d}+{b + 1:03d} ({angle(lights[a], lights[b]):.0f} deg apart): {len(d)} lights, "
              f"the worse of the two {worst:.2f} deg (Lambertian fit from the truth: {best:.2f}); "
              f"{result.lobe or 'diffuse'}", flush=True)
    table.print_all()
    measured = measured_reflectance(probe, mask, photos, saturated, lights, light_powers,
                                    [r["photos"] for r in pair_rows][: 2 if args.quick else args.measured_pairs],
                                    4 if args.quick else len(photos))
    within = float(np.mean(np.array(both) <= 3.0))
    ceiling_within = float(np.mean(np.array(ceiling) <= 3.0))
    summary = dict(
        source=source, photos=len(singles), build_seconds=build, seconds_per_photo=float(np.median(seconds[1:] or seconds)),
        first_photo_seconds=build + seconds[0], pixels=int(probe.T.shape[0]), factor=probe.factor,
        single=dict(median=float(np.median(single)), max=float(np.max(single)), p90=float(np.percentile(single, 90)),
                    highlight_kept=int(np.sum(highlights))),
        lambertian_fit=dict(median=float(np.median(baseline)), max=float(np.max(baseline))),
        pairs=dict(count=pairs, within_3deg=within, median_worse=float(np.median(both)),
                   ceiling_within_3deg=ceiling_within, ceiling_median_worse=float(np.median(ceiling)), rows=pair_rows),
        singles=[dict(photo=int(k) + 1, error=e, baseline=b) for k, e, b in zip(singles, single, baseline)],
        measured=measured,
    )
    print(f"\nprobe, one light: median {summary['single']['median']:.2f} deg, max {summary['single']['max']:.2f}, a "
          f"highlight fitted on {summary['single']['highlight_kept']} of {len(singles)} "
          f"(Lambertian fit: {summary['lambertian_fit']['median']:.2f} / {summary['lambertian_fit']['max']:.2f}); "
          f"two lights: both within 3 deg in {within:.0%} of {pairs} pairs (the Lambertian fit started at the "
          f"truth: {ceiling_within:.0%}, the worse {np.median(ceiling):.2f} deg in the median pair); build {build:.1f} s, "
          f"{summary['seconds_per_photo']:.2f} s per further photo")
    m = measured
    print(f"with the measured reflectance (measured without the photos solved): one light median "
          f"{m['single']['median']:.2f} deg, max {m['single']['max']:.2f} ({m['single']['count']} photos, 4 folds); two "
          f"lights: both within 3 deg in {m['pairs']['within_3deg']:.0%} of {m['pairs']['count']} pairs (the worse "
          f"{m['pairs']['median_worse']:.2f} deg in the median pair); {m['measure_seconds']:.1f} s to measure, "
          f"{m['seconds_per_photo']:.2f} s per photo")
    (args.out / "results.json").write_text(json.dumps(summary, indent=2))
    picture(args.out / "probe.png", photos, maps, lights, probe)
    highlight_picture(args.out / "probe_highlight.png", photos, saturated, lights, probe,
                      [r["photos"] for r in pair_rows][:3])


def measured_reflectance(probe, mask, photos, saturated, lights, powers, pairs, singles: int) -> dict:
    """The probe with the ball's BRDF measured from its other photos (`hj.photo.measure_reflectance`, the
    calibrated lights and powers), never from the photos it solves: each photo alone with the table of
    the three folds it is not in (photo k in fold k mod 4; `singles` photos, spread over the folds), and
    each pair with the table of every photo but its two."""
    M = len(photos)

    def measured(train):
        train = np.asarray(train)
        t0 = time.perf_counter()
        table = hj.photo.measure_reflectance(mask, photos[train], lights[train], powers[train], saturated[train])
        return probe.with_reflectance(table), time.perf_counter() - t0

    chosen = np.linspace(0, M - 1, singles).round().astype(int)
    errors, seconds, measuring = [], [], []
    for fold in range(4):
        view, spent = measured([k for k in range(M) if k % 4 != fold])
        measuring.append(spent)
        for k in chosen[chosen % 4 == fold]:
            t1 = time.perf_counter()
            found = view.solve(photos[k], saturated[k])
            seconds.append(time.perf_counter() - t1)
            errors.append(angle(found.lights.directions[0], lights[k]))
    worse, counts = [], []
    for a, b in pairs:
        a, b = a - 1, b - 1
        view, spent = measured([k for k in range(M) if k not in (a, b)])
        measuring.append(spent)
        t1 = time.perf_counter()
        found = np.asarray(view.solve(photos[a] + photos[b], saturated[a] | saturated[b]).lights.directions)
        seconds.append(time.perf_counter() - t1)
        worse.append(worse_of_two(found, lights[[a, b]]))
        counts.append(len(found))
        print(f"measured reflectance, pair {a + 1:03d}+{b + 1:03d}: {len(found)} lights, the worse of the two "
              f"{worse[-1]:.2f} deg", flush=True)
    return dict(single=dict(count=len(errors), median=float(np.median(errors)), max=float(np.max(errors)),
                            p90=float(np.percentile(errors, 90)), errors=errors),
                pairs=dict(count=len(worse), within_3deg=float(np.mean(np.array(worse) <= 3.0)),
                           median_worse=float(np.median(worse)), worse=worse, lights_found=counts),
                measure_seconds=float(np.median(measuring)), seconds_per_photo=float(np.median(seconds)))


def picture(path, photos, maps, lights, probe):
    """Photos and their maps (tone-mapped), the brightest light found (+) and the calibrated one (x)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = maps[:: max(1, len(maps) // 4)][:4]
    fig, axes = plt.subplots(2, len(shown), figsize=(3.2 * len(shown), 5.0), squeeze=False)
    H, W = probe.grid.shape
    for col, (k, found) in enumerate(shown):
        image = photos[k].mean(axis=-1)
        axes[0, col].imshow(image / max(np.percentile(image, 99.5), 1e-12), cmap="gray", vmin=0, vmax=1)
        axes[0, col].set_title(f"photo {k + 1:03d}")
        env = found.env.mean(axis=-1) if found.env.ndim == 3 else found.env
        axes[1, col].imshow(env / (1 + env), cmap="inferno", extent=(0, W, H, 0))
        for d, marker in ((found.lights.directions[0], "+"), (lights[k], "x")):
            theta, phi = hj.scene.direction_to_angles(np.asarray(d))
            axes[1, col].plot(phi / (2 * np.pi) * W, theta / np.pi * H, marker, color="cyan", ms=12, mew=2)
        axes[1, col].set_title(f"map; + found, x truth ({angle(found.lights.directions[0], lights[k]):.2f} deg)",
                               fontsize=8)
        for ax in axes[:, col]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def highlight_picture(path, photos, saturated, lights, probe, pairs):
    """For pairs of photos summed: the photo, the diffuse model's lights rendered, the lights with the
    fitted highlight rendered, and that fit's residual (all at the highlight fit's size)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(pairs), 4, figsize=(12.0, 3.1 * len(pairs)), squeeze=False)
    T, rows, f = probe.light_T, probe.light_rows, probe.light_factor
    for r, (a, b) in enumerate(pairs):
        a, b = a - 1, b - 1
        photo, out = photos[a] + photos[b], saturated[a] | saturated[b]
        image = probe.averaged(photo, f).mean(axis=-1)  # the photo at the highlight fit's size
        scale = max(np.percentile(image, 99.5), 1e-12)
        panels = [(image, "photo %03d+%03d" % (a + 1, b + 1))]
        for gloss in (False, True):
            found = probe.solve(photo, out, gloss=gloss)
            d = np.asarray(found.lights.directions)
            render = rows.with_reflectance(found.lobe)(d) @ np.asarray(found.lights.power).reshape(len(d), -1)
            worse = worse_of_two(d, lights[[a, b]])
            label = "diffuse model" if found.lobe is None else f"highlight: s {found.lobe.weight:.1f}, a {found.lobe.roughness:.3f}"
            panels.append((np.asarray(T.rows_to_image(render.mean(axis=1))), f"{label}\nthe worse light {worse:.2f} deg"))
        residual = image - panels[-1][0]
        for c, (im, title) in enumerate(panels):
            axes[r, c].imshow(im / scale, cmap="gray", vmin=0, vmax=1)
            axes[r, c].set_title(title, fontsize=8)
        limit = 0.2 * scale
        seen = T.rows_to_image(np.ones(T.shape[0])) > 0
        blank = (probe.averaged(out, f) > 0) | ~seen  # a block with any saturated pixel, as the fit leaves out
        axes[r, 3].imshow(np.where(blank, np.nan, residual), cmap="RdBu_r", vmin=-limit, vmax=limit)
        axes[r, 3].set_title("photo - highlight fit, +-20% of the peak\n(blank: saturated, or not fitted)", fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
