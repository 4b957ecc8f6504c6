"""``sygrid.bench.common.StageCheckpoint``: what a long benchmark resumes from (the digests it is keyed by are
tests/test_bench_stability.py's)."""

from __future__ import annotations

import numpy as np
import pytest

from sygrid.bench.common import StageCheckpoint
from sygrid.errors import ConfigError


def test_finished_stages_are_saved_and_not_measured_again_on_resume(tmp_path):
    path, calls = tmp_path / "run.partial.json", []

    def stage(value):
        def measure():
            calls.append(value)
            return {"value": np.float64(value), "pair": (value, value)}

        return measure

    first = StageCheckpoint(path, {"models": "abc", "n": 3}, resume=True)  # nothing to resume yet
    assert first.run("a", stage(1.0)) == {"value": 1.0, "pair": [1.0, 1.0]}  # as JSON gives it back
    assert path.exists()
    again = StageCheckpoint(path, {"models": "abc", "n": 3}, resume=True)
    assert again.run("a", stage(9.0)) == {"value": 1.0, "pair": [1.0, 1.0]} and calls == [1.0]
    assert again.run("b", stage(2.0))["value"] == 2.0 and calls == [1.0, 2.0]
    again.finish()
    assert not path.exists()
    # not resuming: the old checkpoint is ignored and overwritten by the new run's first stage
    StageCheckpoint(path, {"models": "abc", "n": 3}, resume=True).run("a", stage(1.0))
    fresh = StageCheckpoint(path, {"models": "abc", "n": 3}, resume=False)
    assert fresh.done == {} and fresh.run("a", stage(5.0))["value"] == 5.0


def test_a_checkpoint_of_other_settings_or_a_broken_file_is_refused_by_name(tmp_path):
    path = tmp_path / "run.partial.json"
    StageCheckpoint(path, {"models": "abc", "n": 3}, resume=False).run("a", lambda: 1)
    with pytest.raises(ConfigError, match=r"run\.partial\.json: a checkpoint of a run with other settings \(n\)"):
        StageCheckpoint(path, {"models": "abc", "n": 4}, resume=True)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match=r"run\.partial\.json"):
        StageCheckpoint(path, {"models": "abc", "n": 3}, resume=True)
    assert StageCheckpoint.in_memory().run("x", lambda: [1]) == [1]  # keeps nothing on disk
