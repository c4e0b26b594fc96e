"""Real tables: `reconstruct` on plain, wood-grain and glossy tables, with and without a clean plate.

    python benchmarks/bench_tables.py [--quick] [--out DIR] [--hdri DIR] [--skies NAME ...]

The test set. Each capture is the `reconstruct` stage as a user takes it: the printed board on a
table, a dark teapot (albedo 0.08, 12 cm) standing behind it, seen at 640x480 through a 60-degree
pinhole, lit by a real HDR panorama (`--hdri`: `data_fixtures/hdri/` by default, or the 1k
panoramas of a folder such as Poly Haven's). The photos are path-traced by Mitsuba 3 (`path`,
`max_depth=3`: direct light and one interreflection, box filter; neither `A` nor Embree is
involved). Without Mitsuba the reference renderer (direct light) takes its place and
`results.json` says so. Tables (`--tables`):

- `plain`: matte, uniform albedo 0.65;
- `wood`: matte wood grain (`hj.scenes.wood_texture`, 2 cm stripes) scaled to albedo 0.45-0.85;
- `satin`: albedo 0.65 under a glossy layer (GGX roughness 0.25, index 1.5: Mitsuba's
  `roughplastic`).

Each capture is photographed twice: with the object and as a clean plate (the same view without
it). Each is solved at 128 pixels across on a 32x64 grid with the object stated 8 mm and 10
degrees off its true place, as `examples/real_capture.py` does: with the defaults, with `plate=`,
on the glossy tables with `gloss=0.25` (the truth) and `gloss="auto"`, and on the wood table with
thesis 5.4's joint albedo (`hj.solvers.solve_albedo_illumination` on the default solve's `A` and
photo). `--quick`: one sky, 320x240 photos, 64 pixels across, a 16x32 grid, neither `auto` nor the
joint albedo. The figures are the map's tone-mapped SSIM against the panorama on the grid
(`hj.metrics.env_errors`), the fit's relative residual (what the texture warning reads) and the
glare check's glossy-to-matte residual ratio; `real_tables.png` shows the photos, the plates'
albedo and the maps. Renders are kept in `DIR/renders/` and reused.
"""

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

import hiddenjax as hj
from _report import Table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BOARD = hj.photo.Board(squares=(10, 7), square=0.025, marker=0.019)
FOV = 60.0
EYE, TARGET = (0.06, 0.33, 0.22), (0.0, 0.02, -0.08)
TRUE_PLACE = hj.photo.Placement(0.0, -0.15, 30.0)
STATED_PLACE = hj.photo.Placement(0.008, -0.158, 20.0)
SIZE = 0.12
ALBEDO = 0.65  # the plain table's, and the wood's median
TABLE_SIZE = 8.0
SATIN = 0.25  # GGX roughness of the satin table


def wood(texels: int) -> np.ndarray:
    """Wood grain over the whole table, its albedo stretched to 0.45-0.85 (1st to 99th percentile)."""
    t = hj.scenes.wood_texture(TABLE_SIZE, texels, grain=0.02, mean=0.5, seed=3)
    lo, hi = np.percentile(t, [1, 99])
    return np.clip(0.45 + 0.4 * (t - lo) / (hi - lo), 0.4, 0.9)


def renderer(spp: int):
    """Mitsuba's path tracer when it is installed, else the reference renderer (direct light)."""
    try:
        from hiddenjax.transport._mitsuba import mitsuba_variant, render_panorama_mitsuba

        variant = mitsuba_variant()
        return (f"mitsuba {variant} path tracer, max_depth=3, {spp} spp",
                lambda scene, cam, pano: render_panorama_mitsuba(scene, cam, pano, max_depth=3, spp=spp))
    except ImportError:
        return ("reference renderer, direct light (mitsuba not installed)",
                lambda scene, cam, pano: hj.reference_render(scene, cam, pano, samples=2 * spp, pixel_samples=4))


def sheet(path, maps, truths, photos, cases):
    """One row per sky and table: the photo, the plate's albedo (where taken), the default map, the map
    with the plate, with the glossy model (satin), and the truth on the grid."""
    score = {(c["sky"], c["table"], c["solve"]): c["env_errors"]["ssim_tm"] for c in cases if "env_errors" in c}
    panels, columns = [], 6
    for sky, truth in truths.items():
        white = float(np.percentile(truth[: truth.shape[0] // 2], 99))
        for name in ("plain", "wood", "satin"):
            if (sky, name, "default") not in maps:
                continue
            row = [(f"{sky}, {name} table", photos[(sky, name, "photo")]),
                   ("plate's albedo (relative)", maps.get((sky, name, "plate albedo"), np.full((2, 2), np.nan)),
                    "radiance", 2.0)]
            for solve in ("default", "plate", "gloss 0.25"):
                env = maps.get((sky, name, solve))
                row.append((f"{solve}: tm-SSIM {score[(sky, name, solve)]:.3f}" if env is not None else f"({solve})",
                            env if env is not None else np.full((2, 4), np.nan), "radiance", white))
            row.append(("truth", truth, "radiance", white))
            panels += row
    hj.io.contact_sheet(path, panels, height=160, columns=columns)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_tables"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--hdri", type=Path, default=ROOT / "data_fixtures" / "hdri", help="folder of .hdr panoramas")
    parser.add_argument("--skies", nargs="+", help="panoramas' names (default immenstadter_horn lebombo; "
                                                    "--quick: the first)")
    parser.add_argument("--tables", nargs="+", default=["plain", "wood", "satin"], choices=["plain", "wood", "satin"])
    parser.add_argument("--spp", type=int, default=None, help="Mitsuba samples per pixel (default 128; quick 32)")
    args = parser.parse_args(argv)
    args.skies = args.skies or (["immenstadter_horn"] if args.quick else ["immenstadter_horn", "lebombo"])
    hj.enable_compilation_cache()
    out = args.out
    (out / "renders").mkdir(parents=True, exist_ok=True)
    W, H = (320, 240) if args.quick else (640, 480)
    width, grid = (64, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    spp = args.spp or (32 if args.quick else 128)
    how, render = renderer(spp)
    if how.startswith("reference") and "satin" in args.tables:
        print("the reference renderer is diffuse: the satin table needs Mitsuba (pip install mitsuba); left out")
        args.tables = [t for t in args.tables if t != "satin"]
    f = W / (2 * np.tan(np.radians(FOV) / 2))
    intr = hj.photo.Intrinsics(np.array([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1.0]]), np.zeros(5), W, H)
    camera = hj.Camera.look_at(EYE, TARGET, (0, 1, 0), fov=FOV, width=W, height=H)
    base = hj.photo.object_mesh("teapot", size=SIZE)
    obj = hj.photo.place(base, TRUE_PLACE)
    textures = {"plain": ALBEDO, "wood": wood(1024 if args.quick else 4096), "satin": ALBEDO}
    results = dict(renderer=how, photo_size=[W, H], solve_width=width, grid=list(grid.shape), cases=[])
    maps, truths, photos_shown = {}, {}, {}
    table = Table()
    table.append(("sky", "table", "solve", "tm-SSIM", "residual", "glossy/matte", "roughness", "warns", "seconds"))
    for sky in args.skies:
        path = args.hdri / f"{sky}.hdr"
        path = path if path.exists() else args.hdri / f"{sky}_1k.hdr"
        pano = hj.io.read_hdr(path)
        truth = truths[sky] = grid.downsample(pano)
        for name in args.tables:
            photos = {}
            for kind, mesh in (("photo", obj), ("plate", None)):
                file = out / "renders" / f"{sky}_{name}_{kind}_{W}_{spp}.exr"
                if not file.exists():
                    scene = hj.photo.capture_test_scene(BOARD, mesh, table=textures[name], table_size=TABLE_SIZE,
                                                        roughness=SATIN if name == "satin" else None)
                    hj.io.write_exr(file, render(scene, camera, pano))
                photos[kind] = photos_shown[(sky, name, kind)] = hj.io.read_exr(file)
            solves = {"default": {}, "plate": dict(plate=photos["plate"])}
            if name != "wood":
                solves["gloss 0.25"] = dict(gloss=SATIN)
                if not args.quick:
                    solves["gloss auto"] = dict(gloss="auto")
            for solve, options in solves.items():
                t0 = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    rec = hj.photo.reconstruct(BOARD, photos["photo"], intr, base, STATED_PLACE, width=width,
                                               grid=grid, albedo=ALBEDO, **options)
                seconds = time.perf_counter() - t0
                named = [str(w.message) for w in caught if "--plate" in str(w.message) or "--gloss" in str(w.message)]
                said = "; ".join(sorted({"plate" if "clean plate" in m else "gloss" for m in named}))
                errors = hj.metrics.env_errors(rec.env, truth)
                maps[(sky, name, solve)] = rec.env
                if solve == "plate":
                    maps[(sky, name, "plate albedo")] = np.where(rec.plate.valid[..., None], rec.plate.albedo, np.nan)
                results["cases"].append(dict(sky=sky, table=name, solve=solve, env_errors=errors, residual=rec.residual,
                                             glare=rec.glare, roughness=rec.roughness, warnings=said, seconds=seconds))
                if name == "wood" and solve == "default" and not args.quick:  # thesis 5.4's joint albedo
                    t1 = time.perf_counter()
                    joint = hj.solvers.solve_albedo_illumination(rec.T, rec.photo[None], throw=False)
                    env = np.asarray(joint.env)[0]
                    extra = dict(env_errors=hj.metrics.env_errors(env, truth), seconds=time.perf_counter() - t1,
                                 converged=bool(joint.converged))
                    results["cases"].append(dict(sky=sky, table=name, solve="joint albedo", **extra))
                    table.append((sky, name, "joint albedo", f"{extra['env_errors']['ssim_tm']:.3f}", "-", "-", "-",
                                  "-", f"+{extra['seconds']:.1f}"))
                table.append((sky, name, solve, f"{errors['ssim_tm']:.3f}", f"{rec.residual:.3f}",
                              "-" if rec.glare is None else f"{rec.glare:.2f}",
                              str(rec.roughness), said or "-", f"{seconds:.1f}"))
    table.print_all()
    sheet(out / "real_tables.png", maps, truths, photos_shown, results["cases"])
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"photos: {how}; wrote {out}/results.json")
    return results


if __name__ == "__main__":
    main()
