"""tools/sim_recording: the truth-pose rate comes from the typed [zenoh] settings, as in a run."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
from conftest import DEFAULT_CONFIG
from koala_bridge.core.errors import ConfigError
from koala_bridge.runtime.settings import load_config
from koala_bridge.tools.sim_recording import record_simulator


@pytest.mark.parametrize("bad, words", [
    (0.0, "pose_rate_hz"),      # was a ZeroDivisionError
    ("50", "pose_rate_hz"),     # was read as 50.0 by float()
])
def test_the_pose_rate_is_read_with_the_typed_settings(
    tmp_path: Path, bad: object, words: str
) -> None:
    config = copy.deepcopy(load_config(DEFAULT_CONFIG))
    config["zenoh"]["pose_rate_hz"] = bad
    with pytest.raises(ConfigError, match=words):
        record_simulator(config, tmp_path / "run.mcap", 0.1)
    assert not (tmp_path / "run.mcap").exists()
