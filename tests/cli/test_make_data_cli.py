"""posernet-make-data end to end: Hydra config, presets, summary, clear errors, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

SMALL = [
    "dataset.small.graph_size=4",
    "dataset.small.train=1",
    "dataset.small.val=1",
    "dataset.small.test=1",
    "dataset.large.train=0",
    "dataset.large.test=0",
    "workers=1",
    "progress=false",
]


def cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "posernet.cli.make_data", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(p: subprocess.Popen) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=300)
    return p.returncode, out, err


def test_generates_prints_summary_and_refuses_to_overwrite(tmp_path: Path):
    out = tmp_path / "ds"
    code, stdout, stderr = finish(cli("dataset=tiny", f"out_dir={out}", *SMALL))
    assert code == 0, stderr
    m = json.loads((out / "manifest.json").read_text())
    assert m["preset"] == "tiny" and m["composition"]["small"]["train"]["graphs"] == 2
    assert "KP  paper" in stdout and "small test graphs" in stdout
    assert (out / "small/test/fire.pt").is_file()

    # second run: refused with one line, no traceback
    code, _, stderr = finish(cli("dataset=tiny", f"out_dir={out}", *SMALL))
    assert code == 1 and "already exists" in stderr and "Traceback" not in stderr


def test_preset_alias_with_overrides_and_json_export(tmp_path: Path):
    out = tmp_path / "ds"
    code, _, stderr = finish(
        cli("preset=tiny", f"out_dir={out}", "export_json=true", "dataset.scenes=[chess]", *SMALL)
    )
    assert code == 0, stderr
    m = json.loads((out / "manifest.json").read_text())
    assert m["preset"] == "tiny" and m["splits"]["small"]["train"] == ["chess"]
    assert m["config"]["small"]["graph_size"] == 4
    if "json" in m:
        assert (out / m["json"]["small"]).is_file()


def test_bad_options_fail_cleanly(tmp_path: Path):
    bad = [
        (["dataset.small.graph_size=1"], "dataset.small.graph_size"),
        (["preset=nope"], "unknown dataset preset 'nope'"),
    ]
    # both at once: each run is mostly interpreter start-up
    runs = [
        cli("dataset=tiny", f"out_dir={tmp_path / str(k)}", "progress=false", *args)
        for k, (args, _) in enumerate(bad)
    ]
    for k, (p, (_, message)) in enumerate(zip(runs, bad, strict=True)):
        code, _, stderr = finish(p)
        assert code == 1, stderr
        assert message in stderr and "Traceback" not in stderr
        assert not (tmp_path / str(k) / "manifest.json").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["dataset.keypoints.outlier_rate=2.0"], "dataset.keypoints.outlier_rate"),
        (["workers=0"], "workers"),
        (["dataset.sequences.val_fraction=-1"], "dataset.sequences.val_fraction"),
    ],
)
def test_execute_reports_user_errors_in_one_line(tmp_path, capsys, args, message):
    from hydra import compose, initialize_config_dir

    from posernet.cli import CONFIG_DIR
    from posernet.cli.make_data import execute

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("make_data", overrides=["dataset=tiny", f"out_dir={tmp_path}", *args])
    assert execute(cfg) == 1
    err = capsys.readouterr().err
    assert err.startswith("posernet-make-data: error:") and message in err
    assert len(err.strip().splitlines()) == 1
