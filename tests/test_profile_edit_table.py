"""benchmarks.profile_edit's phase table: loop phases get their share of the loop, one-off phases a dash."""
from types import SimpleNamespace

from benchmarks.profile_edit import _print


def test_one_off_phases_have_no_share_and_loop_phases_sum_to_their_totals(capsys):
    timer = SimpleNamespace(seconds={"step: backward": 3.0, "step: optimiser": 1.0, "update: editor": 4.0,
                                     "checkpoint: save": 0.5})
    result = {"label": "variant", "total": 10.0, "timer": timer, "updates": 2, "iterations": 20}
    _print(result)
    rows = {line.split("  ")[1].strip(): line for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    assert "nan" not in "".join(rows.values())
    assert rows["checkpoint: save"].split()[-3:] == ["-", "500", "ms"]
    assert "30.0%" in rows["step: backward"] and "150.0 ms/it" in rows["step: backward"]
    assert "40.0%" in rows["step total"] and "200 ms/it" in rows["step total"]           # 4 s over 20 iterations
    assert "40.0%" in rows["update total"] and "2000 ms/upd" in rows["update total"]     # 4 s over 2 updates
