"""The `station` command line: bad input gives one clear line and an exit code, never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def station(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "station.cli", *args], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("args, code, message", [
    (["start"], 2, "one of the arguments --robot --naoqi is required"),
    (["start", "--robot", "sim", "--max-duration", "-5"], 2, "expected a positive number"),
    (["carve", "x.mcap", "--tolerance", "-1"], 2, "expected an integer >= 0"),
    (["replay", "/nonexistent/run.mcap"], 1, "No such file"),
])
def test_usage_errors(args, code, message):
    result = station(*args)
    assert result.returncode == code and message in result.stderr and "Traceback" not in result.stderr


def test_config_error_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("mission:\n  search_turn_rate: fast\n")
    result = station("start", "--robot", "sim", "--config", str(bad), "--out", str(tmp_path / "run"))
    assert result.returncode == 2
    assert f"{bad}: mission.search_turn_rate: expected a number" in result.stderr and "Traceback" not in result.stderr


def test_not_a_log(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    for command in ("replay", "carve", "report"):
        result = station(command, str(junk))
        assert result.returncode == 1 and str(junk) in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_unreachable_robot_writes_result(tmp_path):
    override = tmp_path / "o.yaml"
    override.write_text("station:\n  port: 9\n  bridge_timeout: 1.0\n")
    result = station("start", "--robot", "127.0.0.1", "--config", str(override), "--out", str(tmp_path / "run"))
    assert result.returncode == 1 and "no info from the bridge" in result.stderr
    assert json.loads((tmp_path / "run" / "result.json").read_text())["outcome"] == "bridge_unavailable"
