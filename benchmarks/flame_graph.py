"""A flame graph (PNG) of one function's calls from a pyinstrument profile: the loop's cycle as
``benchmarks/loop_cycle.py --profile FILE --flame PNG`` records it.

Each box is a function called (directly or not) from ``LoopRunner.cycle``; its width is its share of
the cycle's wall time over the profiled window, its children stand on it. Colours say what part of
the stack the code belongs to (waiting for frames or the period, the bus and the drives, the EKF,
the law and the limiter, the recording and telemetry, the rest). pyinstrument samples the loop
thread's stack every 0.2 ms of wall time, so waits show as wide as they last.
"""
from __future__ import annotations

from pathlib import Path

#: (label, colour, what selects it: substrings of the function name or of its file's path)
GROUPS = (
    ("waiting (frames, period, locks)", "#bdbdbd", ("acquire", "wait", "sleep", "select", "[await]")),
    ("bus, drives (drivers/, canopen, python-can, sim/)", "#6baed6", ("drivers/", "canopen", "/can/", "sim/")),
    ("EKF (estimation/)", "#74c476", ("estimation/", "feedback.py")),
    ("law, limiter, supervisor (control/, controllers, supervisor)", "#fd8d3c",
     ("control/", "controllers.py", "supervisor.py", "tracking.py")),
    ("recording, telemetry, JSON", "#9e9ac8", ("recording", "telemetry", "json/", "mcap")),
)
OTHER = ("the loop and the rest", "#e7cb94")


def _group(frame) -> tuple[str, str]:
    where = f"{frame.file_path or ''} {frame.function or ''}"
    for label, colour, keys in GROUPS:
        if any(k in where for k in keys):
            return label, colour
    return OTHER


def find(frame, function: str, file_end: str):
    """The heaviest frame running ``function`` in a file ending ``file_end`` (None: none)."""
    best, stack = None, [frame]
    while stack:
        f = stack.pop()
        if f.function == function and (f.file_path or "").endswith(file_end):
            if best is None or f.time > best.time:
                best = f
            continue
        stack.extend(f.children)
    return best


def render(root, path: Path, title: str, min_share: float = 0.004, max_depth: int = 14) -> dict:
    """Draw ``root``'s call tree as a flame graph into ``path`` (PNG); returns the top-level shares."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    total = root.time
    fig, ax = plt.subplots(figsize=(16, 7.5), dpi=110)
    used = {}

    def draw(f, x0: float, depth: int, parent=OTHER) -> None:
        w = f.time / total
        if w < min_share or depth > max_depth:
            return
        label, colour = parent if f.is_synthetic or not depth else _group(f)  # [self] time: its caller's
        used[label] = colour
        ax.add_patch(Rectangle((x0, depth), w, 0.92, facecolor=colour, edgecolor="white", linewidth=0.5))
        name = f.function or "?"
        if w > 0.035:
            short = (f.file_path_short or "").rsplit("/", 2)
            where = "/".join(short[-2:]) if short else ""
            ax.text(x0 + 0.003, depth + 0.46, f"{name} ({100 * w:.0f} %)" + (f"  {where}" if w > 0.12 else ""),
                    va="center", ha="left", fontsize=7, clip_on=True)
        x = x0
        for c in sorted(f.children, key=lambda c: -c.time):
            draw(c, x, depth + 1, (label, colour))
            x += c.time / total

    draw(root, 0.0, 0)
    depth = max_depth + 1
    ax.set_xlim(0, 1)
    ax.set_ylim(0, depth)
    ax.set_xlabel("share of the loop thread's wall time in LoopRunner.cycle over the window")
    ax.set_ylabel("call depth below the cycle")
    ax.set_title(title, fontsize=10)
    ax.set_yticks([])
    ax.legend(handles=[Patch(facecolor=c, label=lbl) for lbl, c in used.items()], loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return {c.function: round(c.time / total, 3) for c in sorted(root.children, key=lambda c: -c.time)[:12]}


def cycle_flame(session, path: Path, title: str) -> dict:
    """``render`` of ``LoopRunner.cycle`` in a pyinstrument session (``Profiler.last_session``)."""
    from pyinstrument import processors

    root = session.root_frame()
    for step in (processors.aggregate_repeated_calls, processors.merge_consecutive_self_time):
        root = step(root, options={})  # one box per call path, not one per call
    cycle = find(root, "cycle", "runtime/loop.py")
    if cycle is None:
        raise ValueError("the profile holds no LoopRunner.cycle frame")
    return render(cycle, path, title)
