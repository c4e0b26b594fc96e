"""Downsample the development HDR panoramas (1024x512, Poly Haven, CC0) to the 256x128 copies here.

    python data_fixtures/hdri/make_hdri.py /path/to/hdri/folder

Each copy is the solid-angle area average of the original (`EnvGrid(128, 256).downsample`), so
every direction keeps its power; a small sun stays one bright pixel of 1.4 degrees. One sky with a
small sun, immenstadter_horn, is also kept at 512x256 (`immenstadter_horn_512.hdr`), the truth of
the scale benchmark's finest grid.
"""

import sys
from pathlib import Path

import hiddenjax as hj

HERE = Path(__file__).resolve().parent
NAMES = ("adams_place_bridge", "dikhololo_night", "forest_slope", "immenstadter_horn", "lebombo",
         "potsdamer_platz", "studio_small_03")


def main(source: str):
    grid = hj.EnvGrid(height=128, width=256)
    for name in NAMES:
        pano = hj.io.read_hdr(Path(source) / f"{name}_1k.hdr")
        hj.io.write_hdr(HERE / f"{name}.hdr", grid.downsample(pano))
        print(name, pano.shape, "->", grid.shape)
    pano = hj.io.read_hdr(Path(source) / "immenstadter_horn_1k.hdr")
    hj.io.write_hdr(HERE / "immenstadter_horn_512.hdr", hj.EnvGrid(256, 512).downsample(pano))


if __name__ == "__main__":
    main(sys.argv[1])
