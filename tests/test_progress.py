"""Progress lines without a terminal: periodic, with done/total and an ETA from an injected clock."""

from __future__ import annotations

import io

from dpmhw.progress import Progress, format_duration


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_log_lines_every_few_seconds_with_eta():
    out, clock = io.StringIO(), FakeClock()
    with Progress(out, every_s=5.0, clock=clock) as progress:
        task = progress.task("rendering 64×48", total=10)
        for i in range(1, 11):
            clock.t += 2.0  # 2 s per step: a line at 6 s (3 steps), 12 s (6), 18 s (9), and when done
            task.update(i)
    lines = out.getvalue().splitlines()
    assert lines == [
        "rendering 64×48: 0/10 (0 %), 0 s elapsed, ETA unknown",
        "rendering 64×48: 3/10 (30 %), 6 s elapsed, ETA 14 s",
        "rendering 64×48: 6/10 (60 %), 12 s elapsed, ETA 8 s",
        "rendering 64×48: 9/10 (90 %), 18 s elapsed, ETA 2 s",
        "rendering 64×48: 10/10 (100 %), done in 20 s",
    ]


def test_callback_keeps_one_task_per_description():
    out, clock = io.StringIO(), FakeClock()
    with Progress(out, every_s=1.0, clock=clock) as progress:
        for desc in ("a", "b"):
            for i in range(1, 4):
                clock.t += 1.0
                progress.callback(desc, i, 3)
    text = out.getvalue()
    assert text.count("a: ") == 3 and "a: 3/3 (100 %), done in 2 s" in text and "b: 3/3 (100 %), done in 2 s" in text


def test_bar_on_a_terminal_prints_no_log_lines():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    out = Tty()
    with Progress(out) as progress:
        assert progress.use_bar
        progress.task("x", total=2).update(2)
    assert "x: 2/2" not in out.getvalue()


def test_format_duration():
    assert [format_duration(s) for s in (0.4, 59, 61, 3600 + 125)] == ["0 s", "59 s", "1 min 01 s", "1 h 02 min"]
