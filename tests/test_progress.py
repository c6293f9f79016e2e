import io

from efficienttrack.core.progress import ProgressDisplay, format_fields


class Clock:
    """A hand-driven monotonic clock (seconds)."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_plain_lines_at_the_interval_and_at_the_end_when_not_a_terminal():
    stream, clock = io.StringIO(), Clock()
    with ProgressDisplay(stream=stream, interval=10.0, clock=clock) as bar:
        task = bar.add_task("train model", total=100, completed=20, loss=float("nan"))
        for step in range(21, 101):
            clock.now += 0.5  # 40 steps in 20 s
            bar.update(task, completed=step, loss=1.0 / step)
    lines = stream.getvalue().splitlines()
    # a line every 10 s (after steps 40 and 60 … 100), each with the count, the fields, the time and the time left
    assert lines[0] == "train model 40/100 loss 0.025 (10 s, ~30 s left)"
    assert lines[1] == "train model 60/100 loss 0.01667 (20 s, ~20 s left)"
    assert lines[-1] == "train model 100/100 loss 0.01 (40 s)"
    assert len(lines) == 5


def test_plain_lines_show_every_task():
    stream, clock = io.StringIO(), Clock()
    with ProgressDisplay(stream=stream, interval=10.0, clock=clock) as bar:
        passes = bar.add_task("collecting (passes)", total=2)
        for k in range(2):
            steps = bar.add_task(f"pass {k + 1}", total=30)
            for _ in range(30):
                clock.now += 1.0
                bar.advance(steps)
            bar.remove_task(steps)
            bar.advance(passes)
    lines = stream.getvalue().splitlines()
    assert "collecting (passes) 0/2 (10 s)" in lines and "pass 1 10/30 (10 s, ~20 s left)" in lines
    assert "collecting (passes) 1/2 (40 s, ~40 s left)" in lines and "pass 2 10/30 (10 s, ~20 s left)" in lines
    assert lines[-1] == "collecting (passes) 2/2 (60 s)"  # the end: a last line for each task still shown


def test_disabled_shows_nothing():
    stream, clock = io.StringIO(), Clock()
    with ProgressDisplay(False, stream=stream, interval=0.0, clock=clock) as bar:
        task = bar.add_task("x", total=3)
        bar.advance(task, 3)
    assert stream.getvalue() == ""


def test_format_fields():
    assert format_fields({"loss": 0.0123456, "pass": 3}) == "loss 0.01235 pass 3"


def test_a_resumed_task_counts_its_time_left_from_where_it_resumed():
    stream, clock = io.StringIO(), Clock()
    with ProgressDisplay(stream=stream, interval=10.0, clock=clock) as bar:
        task = bar.add_task("sac open (steps)", total=1000)
        clock.now += 5.0  # restoring the saved state
        bar.resume(task, completed=800)
        for step in range(801, 901):
            clock.now += 0.25  # 4 steps a second
            bar.update(task, completed=step)
    lines = stream.getvalue().splitlines()
    # 20 steps in the 5 s since it resumed, 180 to go; the 800 restored steps are not this run's rate
    assert lines[0] == "sac open (steps) 820/1,000 (5 s, ~45 s left)"


def test_large_counts_are_shown_in_full():
    stream = io.StringIO()
    with ProgressDisplay(stream=stream, interval=10.0, clock=Clock()) as bar:
        bar.add_task("ppo open (steps)", total=12_361_696, completed=1_559_232)
    assert stream.getvalue().splitlines() == ["ppo open (steps) 1,559,232/12,361,696 (0 s)"]
