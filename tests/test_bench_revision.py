"""benchmarks.revision: the before/after harness of benchmarks.profile_edit and profile_render_cache
(parsing what every version of the profiles prints, and a clear refusal for a commit the history lacks)."""
import pytest

from benchmarks.profile_render_cache import format_table
from benchmarks.revision import (
    RevisionUnavailable,
    parse_edit_profile,
    parse_render_cache_profile,
    profile_revision,
)

# benchmarks.profile_edit's summary lines as printed at 25ad900 and since (abridged: phase rows elided).
PRINTED = """\
DF+SA+CCI (dual field): 100 iterations, 10 view updates, 16.8 s loop (per iteration 168 ms)
  phase                                             total s  share     per unit
  step: backward                                       3.33  19.8%   33.3 ms/it
  update: editor                                       0.10   0.6%     10 ms/upd
  step total                                          10.04  59.7%       100 ms/it
  update total                                         6.78  40.3%       678 ms/upd
  estimated edit stage at the CPU preset (2000 iterations, 200 updates): 5.6 min (+ probes and checkpoints)


baseline (single field): 100 iterations, 10 view updates, 12.0 s loop (per iteration 120 ms)
  step total                                           7.61  63.2%        76 ms/it
  update total                                         4.43  36.8%       443 ms/upd

dual / single loop time: 1.40
"""


def test_the_summary_lines_of_a_profile_are_read_per_variant():
    parsed = parse_edit_profile(PRINTED)
    assert parsed["DF+SA+CCI (dual field)"] == {"iteration_ms": 168.0, "step_ms": 100.0, "update_ms": 678.0}
    assert parsed["baseline (single field)"] == {"iteration_ms": 120.0, "step_ms": 76.0, "update_ms": 443.0}
    assert parsed["dual_over_single"] == 1.40


def test_a_revision_the_history_lacks_is_refused_with_its_name():
    with pytest.raises(RevisionUnavailable, match="0000000000000000000000000000000000000bad"):
        profile_revision("0000000000000000000000000000000000000bad", "benchmarks.profile_edit", [])


# benchmarks.profile_render_cache's output as printed at e4fcf92 (before --compare existed).
RENDER_CACHE_PRINTED = """\
cores: 2, kernel threads: 1 (torch: 1), load 0.67; timings include other load
f_S from /tmp/dualnerf-profile-edit/campsite-600
campsite 256x192: 2.25M samples in 6 kernel calls, replayed 5x
     model  fitted tables s  cache-sized s  misses share
       f_S            1.426          0.749           47%
      dual            2.498          1.658           34%
"""


def test_the_render_cache_table_is_read_per_model_and_round_trips():
    parsed = parse_render_cache_profile(RENDER_CACHE_PRINTED)
    assert parsed == {"f_S": (1.426, 0.749), "dual": (2.498, 1.658)}
    assert parse_render_cache_profile(format_table(parsed)) == parsed
    assert parse_render_cache_profile("campsite 256x192: 2.25M samples in 6 kernel calls") == {}
