"""Write the bundled procedural occluders to PLY files in this folder.

    python data_fixtures/make_fixtures.py

The meshes come from `hiddenjax.scenes` (built in code; no third-party mesh files), in a unit
frame with +y up, resting on y = 0. `tests/test_fixtures.py` checks these files are up to date.
"""

from pathlib import Path

import hiddenjax as hj

HERE = Path(__file__).resolve().parent


def main():
    for name in sorted(hj.scenes.FIXTURES):
        mesh = hj.scenes.fixture(name)
        path = HERE / f"{name}.ply"
        mesh.export(path, encoding="ascii")
        print(f"{path.name}: {len(mesh.faces)} faces, {len(mesh.vertices)} vertices")


if __name__ == "__main__":
    main()
