"""``benchmarks/flame_graph.py``: a box per call path, as wide as its share of the root's time; the
heaviest matching frame is the one drawn; a profile without the cycle is refused by name."""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import flame_graph  # noqa: E402


@dataclass
class Frame:
    function: str
    time: float
    file_path: str = "otbot_hw/x.py"
    children: list = field(default_factory=list)
    is_synthetic: bool = False

    @property
    def file_path_short(self):
        return self.file_path


def _tree():
    ekf = Frame("step", 0.3, "otbot_hw/estimation/ekf.py", [Frame("[self]", 0.3, "", is_synthetic=True)])
    wait = Frame("acquire", 0.5, "<built-in>")
    small = Frame("tiny", 0.001)
    return Frame("cycle", 1.0, "otbot_hw/runtime/loop.py", [ekf, wait, small, Frame("law", 0.199, "otbot_hw/control/c.py")])


def test_find_takes_the_heaviest_frame_of_that_function_and_file():
    light = Frame("cycle", 0.1, "otbot_hw/runtime/loop.py")
    root = Frame("<module>", 2.0, "x", [light, Frame("serve", 1.5, "d", [_tree()])])
    assert flame_graph.find(root, "cycle", "runtime/loop.py").time == 1.0
    assert flame_graph.find(root, "cycle", "elsewhere.py") is None


def test_render_gives_each_child_its_share_and_writes_a_png(tmp_path):
    out = tmp_path / "f.png"
    shares = flame_graph.render(_tree(), out, "test")
    assert shares == {"acquire": 0.5, "step": 0.3, "law": 0.199, "tiny": 0.001}
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert flame_graph._group(Frame("acquire", 1, "<built-in>"))[0].startswith("waiting")
    assert flame_graph._group(Frame("step", 1, "otbot_hw/estimation/ekf.py"))[0].startswith("EKF")


def test_a_profile_without_the_cycle_is_refused_by_name(tmp_path):
    from pyinstrument import Profiler

    p = Profiler(interval=0.0005)
    p.start()
    sum(i * i for i in range(200000))
    p.stop()
    with pytest.raises(ValueError, match="no LoopRunner.cycle frame"):
        flame_graph.cycle_flame(p.last_session, tmp_path / "x.png", "t")
    assert not (tmp_path / "x.png").exists()
