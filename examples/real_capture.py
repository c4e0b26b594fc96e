"""Real captures, end to end: print a board, calibrate, photograph an object beside it, get the map.

The captures are made here with the project's renderers, so every step can be checked against the
truth: photos of the printed board from eight angles through a lens with barrel distortion
(ray-cast), then the capture itself: a dark teapot standing behind the board on a white table
under a real HDR panorama (`data_fixtures/hdri/`), rendered with all its shadows by the reference
renderer, distorted by the same lens, with camera noise. It is saved three ways: a linear EXR,
an 8-bit sRGB JPEG, and a bracket of three JPEG exposures. Then the commands a user runs:

    hiddenjax board -o board.png --pdf board.pdf
    hiddenjax calibrate board.toml calib_*.exr -o camera.toml --sheet calibration.png
    hiddenjax reconstruct board.toml photo.exr --object teapot --size 0.12 --at 0 -0.15 --yaw 20 \\
        --intrinsics camera.toml --albedo 0.8 -o exr/

(also `photo.jpg`, and the bracket with `--times`). The stated place is off by 8 mm and 10 degrees
on purpose; the outline refinement corrects it. The maps are compared with the panorama on the
grid and with the map solved from the *true* scene (true camera and placement) and the same photo.

    python examples/real_capture.py [--quick] [--out DIR] [--hdri NAME]
"""

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

import hiddenjax as hj
from hiddenjax.cli import main as hiddenjax_command

HDRI = Path(__file__).resolve().parents[1] / "data_fixtures" / "hdri"
BOARD = hj.photo.Board(squares=(10, 7), square=0.025, marker=0.019)
FOV = 60.0
DISTORTION = np.array([-0.05, 0.02, 0.0, 0.0, 0.0])
TRUE_PLACE = hj.photo.Placement(0.0, -0.15, 30.0)
STATED_PLACE = hj.photo.Placement(0.008, -0.158, 20.0)
SIZE = 0.12
ALBEDO = 0.8  # the table's
CALIBRATION_VIEWS = [((0.0, 0.27, 0.18), (0, 1, 0)), ((0.17, 0.22, 0.16), (0.3, 1, 0)),
                     ((-0.17, 0.19, 0.18), (-0.4, 1, 0)), ((0.03, 0.17, 0.27), (0, 1, 0)),
                     ((-0.08, 0.3, 0.06), (0.5, 1, 0.2)), ((0.13, 0.17, -0.17), (0, 1, 0)),
                     ((0.22, 0.17, 0.0), (0, 1, 0.5)), ((-0.06, 0.17, -0.24), (0.3, 1, -0.2))]


def encode_srgb(v):
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def save_jpeg(path, linear, exposure_time):
    from PIL import Image

    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x829A] = float(exposure_time)
    rgb = np.round(encode_srgb(linear) * 255).astype(np.uint8)
    Image.fromarray(rgb).save(path, quality=95, subsampling=0, exif=exif)


def run(*argv):
    code = hiddenjax_command([str(a) for a in argv])
    if code != 0:
        raise SystemExit(f"hiddenjax {argv[0]} failed with status {code}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/real_capture"))
    parser.add_argument("--quick", action="store_true", help="small configuration (about a minute)")
    parser.add_argument("--hdri", default="immenstadter_horn", help="development HDRI in data_fixtures/hdri")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    W, H = (480, 360) if args.quick else (640, 480)
    width, grid = (64, (16, 32)) if args.quick else (128, (32, 64))
    render_samples, render_pixel_samples = (32, 2) if args.quick else (128, 4)
    rng = np.random.default_rng(0)
    f = W / (2 * np.tan(np.radians(FOV) / 2))
    K = np.array([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1.0]])

    # 1. The board, printed.
    run("board", "-o", out / "board.png", "--pdf", out / "board.pdf", "--squares", *BOARD.squares,
        "--square", BOARD.square, "--marker", BOARD.marker)

    # 2. Eight photos of it through the lens; calibrate.
    names = []
    for k, (origin, up) in enumerate(CALIBRATION_VIEWS):
        cam = hj.Camera.look_at(origin, rng.normal(0, 0.01, 3) * [1, 0, 1], up, fov=FOV, width=W, height=H)
        image = hj.photo.render_board_photo(BOARD, cam, distortion=DISTORTION, samples=4)
        names.append(out / f"calib_{k}.exr")
        hj.io.write_exr(names[-1], image + rng.normal(0, 0.01, image.shape).astype(np.float32))
    run("calibrate", out / "board.toml", *names, "-o", out / "camera.toml", "--sheet", out / "calibration.png")
    intr = hj.photo.Intrinsics.load(out / "camera.toml")

    # 3. The capture: rendered with the pinhole, then through the lens, with noise.
    panorama = hj.io.read_hdr(HDRI / f"{args.hdri}.hdr")
    camera = hj.Camera.look_at((0.06, 0.33, 0.22), (0.0, 0.02, -0.08), (0, 1, 0), fov=FOV, width=W, height=H)
    base = hj.photo.object_mesh("teapot", size=SIZE)
    pinhole = hj.photo.render_capture(BOARD, hj.photo.place(base, TRUE_PLACE), camera, panorama,
                                      table=ALBEDO, samples=render_samples, pixel_samples=render_pixel_samples)
    noise = lambda a: (a * (1 + rng.normal(0, 0.005, a.shape))).astype(np.float32)
    photo = noise(hj.photo.distort(pinhole, K, DISTORTION))
    exposure = 0.8 / float(np.percentile(photo, 99))  # seconds: the table's highlights at 80% of full scale
    hj.io.write_exr(out / "photo.exr", photo)  # linear radiance (what a raw developer or an HDR merge gives)
    save_jpeg(out / "photo.jpg", photo * exposure, exposure)
    bracket = [exposure / 4, exposure, exposure * 4]
    for k, t in enumerate(bracket):
        save_jpeg(out / f"bracket_{k}.jpg", photo * t, t)

    # 4. One command per capture.
    common = ["--object", "teapot", "--size", SIZE, "--at", STATED_PLACE.x, STATED_PLACE.z, "--yaw", STATED_PLACE.yaw,
              "--intrinsics", out / "camera.toml", "--albedo", ALBEDO, "--width", width, "--grid", *grid, "-q"]
    run("reconstruct", out / "board.toml", out / "photo.exr", *common, "-o", out / "exr")
    run("reconstruct", out / "board.toml", out / "photo.jpg", *common, "-o", out / "jpeg")
    run("reconstruct", out / "board.toml", *[out / f"bracket_{k}.jpg" for k in range(3)], *common,
        "-o", out / "bracket")

    # 5. The same photo solved with the true scene: the true camera and placement, no refinement.
    small_h = int(round(width * H / W))
    true_cam = hj.Camera.look_at((0.06, 0.33, 0.22), (0.0, 0.02, -0.08), (0, 1, 0), fov=FOV, width=width, height=small_h)
    scene = hj.photo.capture_scene(base, TRUE_PLACE, albedo=ALBEDO)
    mask = hj.photo.table_mask(BOARD, true_cam, objects=hj.photo.place(base, TRUE_PLACE))
    T = hj.transport_matrix(scene, true_cam, hj.EnvGrid(*grid), mask=mask, progress=False)
    small = cv2.resize(noise(pinhole), (width, small_h), interpolation=cv2.INTER_AREA)
    env_true_scene = np.asarray(hj.solve_illumination(T, small).env)
    truth = hj.EnvGrid(*grid).downsample(panorama)

    # 6. Numbers and pictures.
    results = dict(hdri=args.hdri, photo_size=[W, H], solve_width=width, grid=list(grid))
    results["calibration"] = dict(focal_error_percent=100 * (intr.focal[0] / f - 1), rms_px=intr.rms,
                                  principal_point_error_px=np.abs(intr.K[:2, 2] - K[:2, 2]).tolist())
    maps = {"true scene": env_true_scene}
    for name in ("exr", "jpeg", "bracket"):
        r = json.loads((out / name / "results.json").read_text())
        R, t = np.asarray(r["pose"]["R"]), np.asarray(r["pose"]["t"])
        angle = np.degrees(np.arccos(np.clip((np.trace(R @ np.asarray(camera.rotation).T) - 1) / 2, -1, 1)))
        p = r["placement"]
        results[name] = dict(
            board_position_error_mm=1000 * float(np.linalg.norm(t - np.asarray(camera.translation))),
            board_rotation_error_deg=float(angle),
            placement_error_mm=1000 * float(np.hypot(p["x"] - TRUE_PLACE.x, p["z"] - TRUE_PLACE.z)),
            yaw_error_deg=float(p["yaw_deg"] - TRUE_PLACE.yaw),
            outline_iou=r["refinement"]["iou"],
        )
        maps[name] = hj.io.read_exr(out / name / "env.exr")
    for name, env in maps.items():
        results.setdefault(name, {})["env_errors"] = hj.metrics.env_errors(env, truth)
    base_ssim = results["true scene"]["env_errors"]["ssim_tm"]
    for name in ("exr", "jpeg", "bracket"):
        results[name]["ssim_tm_minus_true_scene"] = results[name]["env_errors"]["ssim_tm"] - base_ssim
    results["jpeg_minus_exr_ssim_tm"] = results["jpeg"]["env_errors"]["ssim_tm"] - results["exr"]["env_errors"]["ssim_tm"]
    white = float(np.percentile(truth[: grid[0] // 2], 99))
    panels = [("capture (linear EXR)", photo), ("truth on the grid", truth, "radiance", white)]
    panels += [(f"{name}\ntm-SSIM {results[name]['env_errors']['ssim_tm']:.3f}", env, "radiance", white)
               for name, env in maps.items()]
    hj.io.contact_sheet(out / "real_capture.png", panels, height=200, columns=3)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps({k: v for k, v in results.items() if k not in maps}, indent=1))
    for name in maps:
        print(f"{name:>10}: tm-SSIM {results[name]['env_errors']['ssim_tm']:.3f}")
    print(f"wrote {out}/real_capture.png, the commands' folders exr/ jpeg/ bracket/ (check.png in each)")
    return results


if __name__ == "__main__":
    main()
