"""Two hidden lights behind a wall, from the 1D projections their doorway shadows make (thesis 4.3.3).

A wall with three doorways hides two point lights; the camera sees the floor in front of it.
For the left jamb of each doorway, the floor pixels near its foot are cut into 33 slices by the
planes through the edge; the step in mean radiance from slice to slice is a 1D projection of
the hidden scene onto the edge angle `theta` (32 samples, eq. 4.4-4.6). On the
`theta_0 x theta_1` grid of the first two edges, a non-negative ridge solve explains the
projections. Two edges only fix the marginals: the reconstruction cannot tell the lights from
the two "ghost" cells that pair one light's `theta_0` with the other's `theta_1`. The third
edge sees the cells with parallax and removes the ghosts; the singular values of the forward
matrix show the rank it adds (64 -> 96 for 32 x 32 cells; marginals alone have rank 63, the
different fall-off towards the two edges' receivers adds one weak direction).

The image is rendered by Embree with hard shadows (another renderer than the model inverted),
the receivers' 3D points come from its z-buffer.

    python examples/shadow_projections.py [--quick] [--out DIR]
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import hiddenjax as hj  # noqa: E402
from hiddenjax import shadows as sh  # noqa: E402

LIGHTS = np.array([[-0.6, 0.5, -0.8], [1.0, 0.5, -2.9]])  # behind the wall (z < 0), 0.5 m up
INTENSITIES = np.array([1.0, 10.0])  # W/sr: the far light is brighter
HIDDEN_REGION = np.array([[x, 0.5, z] for x in (-1.5, 2.0) for z in (-0.4, -3.4)])  # where lights may be
RADIUS = 0.4  # receivers within this distance of a jamb's foot


def projections(image, depth, camera, edges, bins=32):
    """One `Projection` per edge from the floor pixels in front of the wall near its foot."""
    points = np.asarray(sh.depth_to_points(depth, camera)).reshape(-1, 3)
    values = np.asarray(image).reshape(-1)
    out, masks = [], []
    for edge in edges:
        d = points - edge[0]
        near = np.isfinite(points).all(axis=1) & (np.abs(d[:, 1]) < 1e-3) & (d[:, 2] > 0.01)
        near &= np.hypot(d[:, 0], d[:, 2]) < RADIUS
        out.append(sh.edge_projection(values[near], points[near], edge, bins,
                                      theta_range=sh.angle_span(HIDDEN_REGION, edge)))
        masks.append(near.reshape(image.shape))
    return out, masks


def grid_position(proj, angles):
    """Fractional bin index of light angles on a projection's grid."""
    return np.mod(np.asarray(angles) - proj.theta[0], 2 * np.pi) / proj.step


def mass_near(rec, cells, radius=1.5):
    """Share of the reconstruction's contribution within `radius` cells of each of `cells (K, 2)`."""
    i, j = np.meshgrid(np.arange(rec.contribution.shape[0]), np.arange(rec.contribution.shape[1]), indexing="ij")
    total = rec.contribution.sum()
    return [float(rec.contribution[np.maximum(np.abs(i - a), np.abs(j - b)) <= radius].sum() / total) for a, b in cells]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/shadow_projections"))
    parser.add_argument("--quick", action="store_true", help="smaller image (seconds)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size = (256, 128) if args.quick else (512, 256)

    (scene, camera), edges = hj.scenes.doorways(width=size[0], height=size[1])
    image = hj.render_point_lights(scene, camera, LIGHTS, INTENSITIES, pixel_samples=4)
    depth = hj.depth_map(scene, camera)
    projs, masks = projections(image, depth, camera, edges)
    hidden_plane = (LIGHTS[0], np.array([0.0, 1.0, 0.0]))
    two = sh.reconstruct_from_projections(projs[:2], hidden_plane)
    three = sh.reconstruct_from_projections(projs, hidden_plane)

    truth = [np.asarray(sh.edge_angle(LIGHTS, e[0], e[1])) for e in edges]
    cells = np.stack([grid_position(projs[0], truth[0]), grid_position(projs[1], truth[1])], -1)
    ghosts = np.stack([cells[:, 0], cells[::-1, 1]], -1)
    rank = lambda s: int(np.sum(s > 1e-6 * s[0]))
    peaks = [[float(np.min(np.abs(np.argmax(p.values) - grid_position(p, t))))] for p, t in zip(projs, truth)]
    results = dict(
        config=dict(image=list(size), bins=32, radius_m=RADIUS, receivers=[int(m.sum()) for m in masks]),
        lights=LIGHTS.tolist(),
        strongest_peak_bins_from_a_light=[p[0] for p in peaks],
        two_edges=dict(rank=rank(two.singular_values), near_lights=mass_near(two, cells),
                       near_ghosts=mass_near(two, ghosts), residual=two.residual, kkt=two.kkt),
        three_edges=dict(rank=rank(three.singular_values), near_lights=mass_near(three, cells),
                         near_ghosts=mass_near(three, ghosts), residual=three.residual, kkt=three.kkt),
    )

    overlay = np.repeat(np.sqrt(np.asarray(image) / np.percentile(image, 99.5)).clip(0, 1)[..., None], 3, -1)
    for m, colour in zip(masks, ([1, 0.3, 0.3], [0.3, 1, 0.3], [0.3, 0.5, 1])):
        overlay[m] = 0.5 * overlay[m] + 0.5 * np.array(colour)
    fig = plt.figure(figsize=(15, 9))
    ax = fig.add_subplot(3, 3, (1, 3))
    ax.imshow(overlay)
    ax.set_title("observed floor (sqrt); receivers of edges 0, 1, 2 in red, green, blue")
    ax.axis("off")
    for k, p in enumerate(projs):
        ax = fig.add_subplot(3, 3, 4 + k)
        ax.plot(p.theta, p.values, ".-")
        for t in truth[k]:
            ax.axvline(p.theta[0] + np.mod(t - p.theta[0], 2 * np.pi), color="r", lw=0.8)
        ax.set_title(f"edge {k}: 1D projection (red: true lights)")
        ax.set_xlabel("theta (rad)")
    for k, (rec, name) in enumerate(((two, "two edges"), (three, "three edges"))):
        ax = fig.add_subplot(3, 3, 7 + k)
        ax.imshow(np.where(rec.valid, rec.contribution, np.nan).T, origin="lower", cmap="magma")
        ax.plot(*cells.T, "c+", ms=14, label="lights")
        ax.plot(*ghosts.T, "wx", ms=9, label="ghosts")
        ax.set_title(f"{name}: theta_0 x theta_1 (grey: no valid cell)")
        ax.set_xlabel("theta_0 bin")
        ax.set_ylabel("theta_1 bin")
        ax.legend(loc="upper left", fontsize=7)
    ax = fig.add_subplot(3, 3, 9)
    ax.semilogy(two.singular_values / two.singular_values[0], label=f"two edges (rank {results['two_edges']['rank']})")
    ax.semilogy(three.singular_values / three.singular_values[0],
                label=f"three edges (rank {results['three_edges']['rank']})")
    ax.set_ylim(1e-4, 2)
    ax.set_title("singular values of the forward matrix")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "shadow_projections.png", dpi=90)
    plt.close(fig)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
