"""One error tree (core/errors.py): every project exception is a KoalaBridgeError, under its old
name and import path, and the CLI turns one into a single line, exit 2."""

from __future__ import annotations

import argparse

import pytest
from koala_bridge.calibration.errors import (
    BundleError,
    CalibrationError,
    EffectRegistryError,
    ModelConfigError,
)
from koala_bridge.cli import main as cli_main
from koala_bridge.core import errors
from koala_bridge.core.errors import KoalaBridgeError
from koala_bridge.core.schema import ConfigError
from koala_bridge.core.topics import TopicError
from koala_bridge.drivers.messages import (
    DriverError,
    FrameError,
    TransportClosedError,
    TransportError,
)
from koala_bridge.estimation.errors import DegenerateGeometryError, EstimationError
from koala_bridge.recording.mcap_file import RecordingError, UnsupportedRecordingError
from koala_bridge.runtime.buses import BusOpenError


@pytest.mark.parametrize("cls, bases", [
    (ConfigError, (ValueError,)),
    (TopicError, (ValueError,)),
    (DriverError, ()),
    (FrameError, (DriverError, ValueError)),
    (TransportError, (DriverError, OSError)),
    (TransportClosedError, (TransportError,)),
    (BusOpenError, (TransportError, OSError)),
    (RecordingError, ()),
    (UnsupportedRecordingError, (RecordingError,)),
    (EstimationError, (ValueError,)),
    (DegenerateGeometryError, (EstimationError,)),
    (CalibrationError, ()),
    (BundleError, (CalibrationError,)),
    (ModelConfigError, (CalibrationError,)),
    (EffectRegistryError, (CalibrationError,)),
])
def test_every_project_error_is_in_the_one_tree(cls: type, bases: tuple[type, ...]) -> None:
    assert issubclass(cls, KoalaBridgeError)
    for base in bases:
        assert issubclass(cls, base)


def test_the_old_homes_re_export_the_tree_s_classes() -> None:
    assert ConfigError is errors.ConfigError
    assert TopicError is errors.TopicError
    assert RecordingError is errors.RecordingError
    assert EstimationError is errors.EstimationError
    assert CalibrationError is errors.CalibrationError
    assert (DriverError, FrameError, TransportError) == (
        errors.DriverError, errors.FrameError, errors.TransportError)


def _fake_subcommand(exc: BaseException) -> object:
    class Module:
        @staticmethod
        def add_arguments(parser: argparse.ArgumentParser) -> None:
            pass

        @staticmethod
        def run(args: argparse.Namespace) -> int:
            raise exc

    return Module


@pytest.mark.parametrize("exc", [
    RecordingError("cannot read x.mcap"),
    ConfigError("[run] unknown key 'clok'"),
    BundleError("no bundle at y"),
])
def test_the_cli_prints_a_project_error_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], exc: Exception
) -> None:
    monkeypatch.setattr(cli_main, "_load", lambda name: _fake_subcommand(exc))
    assert cli_main.main(["export"]) == 2
    prefix = "configuration error: " if isinstance(exc, ConfigError) else ""
    assert capsys.readouterr().err == f"koala-bridge export: {prefix}{exc}\n"


def test_the_cli_does_not_swallow_a_bug(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cli_main, "_load", lambda name: _fake_subcommand(KeyError("bug")))
    with pytest.raises(KeyError):
        cli_main.main(["export"])


def test_an_unreadable_endpoints_file_is_a_transport_error(tmp_path: object) -> None:
    from pathlib import Path

    from koala_bridge.tools.monitor import target_from_endpoints_file

    d = Path(str(tmp_path))
    (d / "bad.json").write_text("{not json", encoding="utf-8")
    (d / "other.json").write_text("{}", encoding="utf-8")
    for name, words in [("missing.json", "cannot read the endpoints file"),
                        ("bad.json", "is not an endpoints file"),
                        ("other.json", "is not a koala-bridge endpoints file")]:
        with pytest.raises(TransportError, match=words) as info:
            target_from_endpoints_file(d / name)
        assert isinstance(info.value, OSError)
        assert isinstance(info.value, KoalaBridgeError)
