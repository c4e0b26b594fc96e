"""A desk lamp from one ordinary photo of a pencil and a cup: `hiddenjax lights` as a user runs it.

The photo is what a phone would give: rendered (Embree, box-filtered, two diffuse bounces, 5%
ambient), vignetted (`1 - 0.3 r^2`), scaled to its 99.5th percentile and clipped, gamma-encoded
(2.2) and saved as an 8-bit PNG twice the scene file's size. The scene file describes the desk and the objects with
primitives (`shape = "plane"`, `"cylinder"`) and puts each object 3 mm from its true place. No
reference photo, no mask: `hiddenjax lights scene.toml photo.png --within 1.0 -o lights.json`
leaves out the objects' outline grown by 5 mm, fits the photo's ratio to its own smooth
shading (the direction), then places the lamp in the photo's brightness (its falloff across the
desk, with the tone curve and vignetting fitted, the shadow's direction as a prior), and reports
each light's 95% cone and distance interval. `--lamps 2` adds a far second lamp low at the
side (0.77 m from the objects, about 40 degrees up) and a larger cup: the two lamps' shadows cover most
of the photo's lower half, and `--count 2` fits both (the smooth shading is fitted again under the
found shadows and the search run again on it). `--table satin` puts the desk under a satin layer
(GGX roughness 0.25, index 1.5: the lamp's highlight on it), photographed by Mitsuba's path tracer
(64 samples per pixel; Mitsuba 3 needed), and the scene file says `roughness = 0.4`, a guess:
the falloff is shaded with the layer's lobe and its roughness fitted with the lamp.

Writes `photo.png`, `scene.toml`, `lights.json`, `fit.png` (photo, fitted image, difference) and
`desk_lamp.png` (the desk from above and from the side: the objects, the true lamps, the found
ones with their 95% cones and intervals), and `results.json`.

    python examples/desk_lamp.py [--quick] [--lamps 1|2] [--table matte|satin] [--out DIR]
"""

import argparse
import itertools
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import hiddenjax as hj  # noqa: E402
from hiddenjax.cli import main as cli  # noqa: E402

LAMP = np.array([0.25, 0.45, -0.3])  # metres: 0.6 m from the pencil, 50 degrees up, behind it
SECOND_LAMP = np.array([0.649, 0.524, -0.14])  # `--lamps 2`: 0.77 m from the objects, low at the side
OFFSET = np.array([0.003, 0.0, 0.0])  # where the scene file misplaces the objects
PENCIL = ("cylinder", dict(radius=0.004, height=0.076), np.array([0.0, 0.0, 0.0]))
CUPS = {1: ("cylinder", dict(radius=0.03, height=0.08), np.array([0.08, 0.0, 0.05])),
        2: ("cylinder", dict(radius=0.04, height=0.09), np.array([0.1, 0.0, 0.06]))}  # a larger cup beside two lamps
CAMERA = dict(origin=[0.0, 0.32, 0.30], target=[0.0, 0.0, -0.02], fov=60.0)
SATIN = dict(roughness=0.25, ior=1.5)  # `--table satin`: the true layer; the scene file guesses roughness 0.4


def scene_toml(width: int, height: int, objects, satin: bool = False) -> str:
    """The scene file a user would write: the desk (glossy, of a guessed roughness, if `satin`) and the
    `objects` as primitives, 3 mm off."""
    text = (f"[camera]\nwidth = {width}\nheight = {height}\norigin = {CAMERA['origin']}\n"
            f"target = {CAMERA['target']}\nfov = {CAMERA['fov']}\n\n"
            '[[surface]]\nshape = "plane"\nextent = [0.9, 0.7]\nalbedo = 0.6\n' + ("roughness = 0.4\n" if satin else ""))
    for shape, sizes, place in objects:
        keys = "".join(f"{k} = {v}\n" for k, v in sizes.items())
        text += (f'\n[[surface]]\nshape = "{shape}"\n{keys}observe = false\nalbedo = 0.5\n'
                 f"[surface.transform]\ntranslation = {(place + OFFSET).round(4).tolist()}\n")
    return text


def photograph(width: int, height: int, objects, lamps, satin: bool = False) -> np.ndarray:
    """The faulty 8-bit photo (module docstring) of the true scene under `lamps (L, 3)` of equal
    intensity, `(height, width)` uint8; on a `satin` desk, path-traced by Mitsuba."""
    surfaces = [hj.Surface(hj.scene.primitive("plane", extent=(0.9, 0.7)), 0.6, **(SATIN if satin else {}))]
    for shape, sizes, place in objects:
        mesh = hj.scene.primitive(shape, **sizes)
        mesh.apply_translation(place)
        surfaces.append(hj.Surface(mesh, 0.5, observe=False))
    camera = hj.Camera.look_at(CAMERA["origin"], CAMERA["target"], [0, 1, 0], CAMERA["fov"], width, height)
    if satin:  # a path tracer, not the model fitted: Mitsuba's roughplastic with its interreflections
        from hiddenjax.transport._mitsuba import render_point_lights_mitsuba

        radiance = render_point_lights_mitsuba(hj.Scene(surfaces), camera, lamps, [0.05] * len(lamps), max_depth=4,
                                               spp=64)
    else:
        radiance = hj.render_point_lights(hj.Scene(surfaces), camera, lamps, [0.05] * len(lamps), pixel_samples=9,
                                          bounces=2)
    radiance = radiance + 0.05 * radiance.mean()
    rows, cols = np.mgrid[:height, :width] + 0.5
    r2 = ((rows - height / 2) ** 2 + (cols - width / 2) ** 2) / ((height / 2) ** 2 + (width / 2) ** 2)
    encoded = np.clip(radiance * (1 - 0.3 * r2) / np.percentile(radiance, 99.5), 0, 1) ** (1 / 2.2)
    return np.round(255 * encoded).astype(np.uint8)


def picture(path, found, lamps, objects, order):
    """The desk from above (x, z) and from the side (horizontal distance, height): each found light
    (`order[k]`: the one matched to `lamps[k]`) with its 95% cone and interval, and the true lamps."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    anchor = np.array(found["lights"][0]["from_point"])
    for ax, (i, j, label) in zip(axes, ((0, 2, "z (m)"), (None, 1, "height (m)"))):
        def coords(p):
            p = np.asarray(p) - anchor if i is None else np.asarray(p)
            return (np.hypot(p[..., 0], p[..., 2]) if i is None else p[..., i]), p[..., j] + (anchor[1] if i is None else 0)

        for k, (lamp, colour) in enumerate(zip(lamps, ("tab:orange", "tab:green"))):
            light = found["lights"][order[k]]
            direction = np.array(light["direction"])
            near, far = light["distance_95"]
            ray = anchor + np.linspace(near, far, 2)[:, None] * direction
            ax.plot(*coords(ray), color=colour, lw=6, alpha=0.4, label="95% distance interval" if k == 0 else None)
            half = np.radians(light["angle_95"])
            for sign in (-1, 1):  # the cone's edges in this view's plane
                side = np.cross(direction, [0, 1, 0] if i is not None else [direction[2], 0, -direction[0]])
                side = side / max(np.linalg.norm(side), 1e-12)
                edge = np.cos(half) * direction + sign * np.sin(half) * side
                ax.plot(*coords(np.stack([anchor, anchor + far * edge])), color=colour, lw=0.8)
            ax.plot(*coords(np.array(found["positions"][order[k]])), "o", color=colour, label="found" if k == 0 else None)
            ax.plot(*coords(lamp), "*", color="k", ms=12, label="true lamp" if k == 0 else None)
        for _, sizes, place in objects:
            ax.plot(*coords(place + np.array([0, sizes["height"], 0])), "s", color="tab:blue", ms=4)
        ax.set_xlabel("x (m)" if i is not None else "horizontal distance from the objects (m)")
        ax.set_ylabel(label)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    axes[0].set_title("from above")
    axes[1].set_title("from the side, along each light")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/desk_lamp"))
    parser.add_argument("--quick", action="store_true", help="a 64 x 48 fit instead of 160 x 120")
    parser.add_argument("--lamps", type=int, choices=(1, 2), default=1, help="one lamp (default) or two")
    parser.add_argument("--table", choices=("matte", "satin"), default="matte",
                        help="a matte desk (default) or a satin one, photographed by Mitsuba (module docstring)")
    args = parser.parse_args(argv)
    satin = args.table == "satin"
    if satin:
        try:
            import mitsuba  # noqa: F401
        except ImportError:
            raise SystemExit("--table satin photographs the desk with Mitsuba 3: pip install 'hiddenjax[mitsuba]'")
    args.out.mkdir(parents=True, exist_ok=True)
    width, height = (64, 48) if args.quick else (160, 120)
    lamps = np.stack([LAMP, SECOND_LAMP][:args.lamps])
    objects = [PENCIL, CUPS[args.lamps]]
    hj.io.write_png(args.out / "photo.png", photograph(2 * width, 2 * height, objects, lamps, satin))
    (args.out / "scene.toml").write_text(scene_toml(width, height, objects, satin))
    status = cli(["lights", str(args.out / "scene.toml"), str(args.out / "photo.png"), "--within", "1.0",
                  "--count", str(args.lamps), "-o", str(args.out / "lights.json"), "--png", str(args.out / "fit.png")])
    if status:
        raise SystemExit(status)
    found = json.loads((args.out / "lights.json").read_text())
    positions = np.array(found["positions"])
    order = min(itertools.permutations(range(len(lamps))),  # the found light matched to each true lamp
                key=lambda p: np.sum(np.linalg.norm(positions[list(p)] - lamps, axis=1)))
    results = dict(seconds=found["seconds"], table=args.table, roughness=(found["camera_response"] or {}).get("roughness"),
                   lamps=[])
    for lamp, k in zip(lamps, order):
        light = found["lights"][k]
        true = lamp - np.array(light["from_point"])
        angle = float(np.degrees(np.arccos(np.clip(np.dot(light["direction"], true) / np.linalg.norm(true), -1, 1))))
        results["lamps"].append(dict(true=lamp.tolist(), found=positions[k].tolist(), direction_error_deg=angle,
                                     distance=light["distance"], true_distance=float(np.linalg.norm(true)),
                                     angle_95=light["angle_95"], distance_95=light["distance_95"],
                                     position_error_m=float(np.linalg.norm(positions[k] - lamp))))
        print(f"direction {angle:.2f} deg off (95% cone {light['angle_95']:.1f}); distance {light['distance']:.3f} m "
              f"against {np.linalg.norm(true):.3f} (95%: {light['distance_95'][0]:.3f}-{light['distance_95'][1]:.3f}); "
              f"position {100 * results['lamps'][-1]['position_error_m']:.1f} cm off")
    if satin:
        print(f"the desk's roughness read as {results['roughness']:.3f} (true {SATIN['roughness']}, the scene file's "
              "guess 0.4)")
    picture(args.out / "desk_lamp.png", found, lamps, objects, order)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
