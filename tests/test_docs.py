"""Every Python block of the README, the getting-started page and the guides runs, in page order.

The blocks of one page share a namespace (a page reads top to bottom like one script) and run in a
temporary folder, so the files they write go there. The scene-file guide's TOML block is read with
`hj.load_scene`. Pages whose blocks take minutes are marked slow (CI runs them too).
"""

import re
from pathlib import Path

import numpy as np
import pytest

import hiddenjax as hj

ROOT = Path(__file__).resolve().parents[1]
FAST = ["README.md", "docs/getting-started.md", "docs/guide/objects-as-cameras.md", "docs/guide/hidden-cues.md",
        "docs/guide/shadow-edges.md", "docs/guide/real-captures.md", "docs/guide/large-maps.md",
        "docs/guide/compilation.md", "docs/guide/light-probe.md"]
SLOW = ["docs/guide/uncertain-scenes.md", "docs/guide/around-the-corner.md", "docs/guide/design.md"]


def blocks(page, language="python"):
    text = (ROOT / page).read_text()
    return re.findall(rf"^```{language}\n(.*?)^```", text, flags=re.S | re.M)


def run_page(page, tmp_path, monkeypatch):
    code = blocks(page)
    assert code, f"{page} has no python block"
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    for k, block in enumerate(code):
        exec(compile(block, f"{page} block {k}", "exec"), namespace)


def test_every_guide_is_covered():
    pages = {str(p.relative_to(ROOT)) for p in (ROOT / "docs/guide").glob("*.md") if blocks(str(p.relative_to(ROOT)))}
    assert pages <= set(FAST + SLOW), pages - set(FAST + SLOW)


@pytest.mark.parametrize("page", FAST)
def test_page_runs(page, tmp_path, monkeypatch):
    run_page(page, tmp_path, monkeypatch)


@pytest.mark.slow
@pytest.mark.parametrize("page", SLOW)
def test_long_page_runs(page, tmp_path, monkeypatch):
    run_page(page, tmp_path, monkeypatch)


def test_scene_file_guide_reads(tmp_path):
    toml, desk = blocks("docs/guide/scene-files.md", "toml")
    (tmp_path / "scene.toml").write_text(toml)
    hj.io.write_png(tmp_path / "mask.png", np.ones((128, 128), np.float32))  # the mask image it names
    f = hj.load_scene(tmp_path / "scene.toml")
    assert (f.camera.width, f.camera.height, f.grid.height, f.grid.width) == (128, 128, 32, 64)
    assert len(f.scene) == 1 and np.isclose(float(f.scene[0].albedo), 0.8)
    (tmp_path / "desk.toml").write_text(desk)  # the primitives' example: a desk, a pencil and a book
    f = hj.load_scene(tmp_path / "desk.toml")
    assert [s.observe for s in f.scene] == [True, False, False]
    assert np.isclose(f.scene[1].mesh.bounds[1, 1], 0.076) and np.isclose(f.scene[2].mesh.bounds[1, 1], 0.03)


def test_real_captures_guide_chessboard_file_reads(tmp_path):
    (chess,) = blocks("docs/guide/real-captures.md", "toml")
    (tmp_path / "chess.toml").write_text(chess)
    assert hj.photo.load_board(tmp_path / "chess.toml") == hj.photo.Chessboard(inner=(9, 6), square=0.025)
