"""The package is self-contained: its configs and checkpoint ship in the wheel and the commands
run from an installed wheel, outside the source tree.

The slow test builds the wheel from a copy of the sources (``pip wheel --no-build-isolation``:
the venv's setuptools, no network), installs it with ``--no-deps`` into a fresh folder and runs
the commands with that folder on ``PYTHONPATH`` from an unrelated working directory. A small
runner asserts, inside each command's own process, that every ``posernet`` module it loaded
comes from that folder: the editable install's path entry (a ``.pth`` file) comes after
``PYTHONPATH``, and the runner fails the command if the source tree wins anyway.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "posernet"
COMMANDS = ("posernet-demo", "posernet-make-data", "posernet-train", "posernet-eval",
            "posernet-refine", "posernet-reconstruct")

# Runs a module as ``python -m`` would (or a code string), after and before which every loaded
# posernet module must lie under the install folder argv[1]; exit status 97 if not.
RUNNER = r'''
import os
import runpy
import sys

site = os.path.realpath(sys.argv[1])


def check():
    stray = sorted(
        name for name, mod in list(sys.modules.items())
        if name.split(".")[0] == "posernet" and getattr(mod, "__file__", None)
        and not os.path.realpath(mod.__file__).startswith(site + os.sep)
    )
    if stray:
        sys.stderr.write(f"posernet modules not loaded from {site}: {stray}\n")
        sys.stderr.flush()
        os._exit(97)


import posernet  # noqa: E402

check()
try:
    if sys.argv[2] == "-c":
        exec(compile(sys.argv[3], "<check>", "exec"), {"__name__": "__main__", "site": site})
    else:
        sys.argv = sys.argv[2:]
        runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
finally:
    check()
'''

# In the installed package: presets and configs found through the wheel's own files.
CHECK_CONFIGS = r'''
import os
from hydra import compose, initialize_config_dir
from posernet.conf import config_dir
from posernet.data.synthetic import available_presets, load_preset

assert config_dir() == os.path.join(site, "posernet", "conf"), config_dir()
assert {"tiny", "demo", "easy", "paper"} <= set(available_presets()), available_presets()
opts = load_preset("tiny")
assert opts.name == "tiny" and opts.small.graph_size == 4, opts
with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
    for name in ("make_data", "train", "eval", "refine", "demo", "reconstruct"):
        compose(name)
print("configs ok")
'''


def _setuptools_version() -> tuple[int, ...]:
    try:
        return tuple(int(p) for p in metadata.version("setuptools").split(".")[:2])
    except (metadata.PackageNotFoundError, ValueError):
        return ()


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the sources (no stale ``build/`` folder, none left in
    the checkout)."""
    if _setuptools_version() < (77,):
        pytest.fail("building the wheel offline needs setuptools>=77 in this environment "
                    "(the [dev] extra); found " + (metadata.version("setuptools")
                                                  if _setuptools_version() else "none"))
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "posernet-src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "src", src / "src",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info"))
    out = tmp / "dist"
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
         "--no-index", "--disable-pip-version-check", "-q", "-w", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (whl,) = out.glob("posernet-*.whl")
    return whl


@pytest.mark.slow
def test_wheel_carries_configs_and_checkpoint(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    yaml = {f"posernet/conf/{p.relative_to(PACKAGE / 'conf').as_posix()}"
            for p in (PACKAGE / "conf").rglob("*.yaml")}
    assert len(yaml) >= 30 and "posernet/conf/dataset/tiny.yaml" in yaml
    assert yaml <= names, sorted(yaml - names)
    assert "posernet/conf/__init__.py" in names
    ckpts = {f"posernet/checkpoints/{p.name}" for p in (PACKAGE / "checkpoints").glob("*.ckpt")}
    assert "posernet/checkpoints/posernet_synthetic_kp.ckpt" in ckpts
    assert ckpts <= names, sorted(ckpts - names)
    (entry_points,) = (n for n in names if n.endswith(".dist-info/entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    for command in COMMANDS:
        assert f"{command} = " in text, command
    # the library only: no research record, no results, no tests in the wheel
    assert not [n for n in names if n.startswith(("research/", "results/", "tests/",
                                                  "benchmarks/"))]
    assert not [n for n in names if "vary_" in n or "heldout" in n]
    assert "posernet/experiments/adaptive.py" not in names
    assert "posernet/conf/scale/quick.yaml" in names


@pytest.mark.slow
def test_commands_run_from_the_installed_wheel(wheel, tmp_path):
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index",
         "--disable-pip-version-check", "-q", "--target", str(site), str(wheel)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (site / "posernet" / "conf" / "dataset" / "tiny.yaml").is_file()
    runner = tmp_path / "run_installed.py"
    runner.write_text(RUNNER, encoding="utf-8")
    work = tmp_path / "work"  # not the checkout: nothing found relative to the cwd
    work.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "POSERNET_CONFIG_DIR")}
    env.update(PYTHONPATH=str(site), PYTHONNOUSERSITE="1")

    def run(*args: str) -> str:
        p = subprocess.run([sys.executable, str(runner), str(site), *args], cwd=work, env=env,
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, f"{args}: exit {p.returncode}\n{p.stdout}\n{p.stderr}"
        return p.stdout

    assert "configs ok" in run("-c", CHECK_CONFIGS)

    data = tmp_path / "d"
    run("posernet.cli.make_data", "dataset=tiny", f"out_dir={data}", "progress=false")
    assert json.loads((data / "manifest.json").read_text())["preset"] == "tiny"
    assert sorted(p.name for p in (data / "small" / "test").glob("*.pt"))

    out = tmp_path / "r"
    run("posernet.cli.refine", f"input={data}", f"out_dir={out}")  # the shipped checkpoint
    refined = json.loads((out / "refined.json").read_text())
    assert len(refined["graphs"]) == 4  # the tiny preset's small test graphs
    assert Path(refined["checkpoint"]).resolve().is_relative_to(site.resolve())
    assert (out / "table.md").is_file()

    # fine-tune the shipped checkpoint inside the wheel on the generated data (one epoch)
    run_dir = tmp_path / "ft"
    log = run("posernet.cli.train", f"data.root={data}", "model=adaptive", "model.net.depth=3",
              "model.net.node_hidden=64", "model.net.mlp_hidden=64", "init_from=shipped",
              "trainer.max_epochs=1", "trainer.enable_progress_bar=false", "data.batch_size=2",
              f"hydra.run.dir={run_dir}")
    (line,) = [ln for ln in log.splitlines() if ln.startswith("Fine-tuning the network of ")]
    assert Path(line.split(" of ", 1)[1].split(" (")[0]).resolve().is_relative_to(site.resolve())
    assert (run_dir / "checkpoints" / "last.ckpt").is_file()


# ------------------------------------------------------------------------------ fast checks


def test_config_dir_override(tmp_path, monkeypatch):
    """POSERNET_CONFIG_DIR replaces the shipped tree, for Hydra's path and the presets alike."""
    from posernet.conf import config_dir
    from posernet.data.synthetic import available_presets, load_preset

    shipped = Path(config_dir())
    assert shipped == PACKAGE / "conf"
    conf = tmp_path / "conf"
    shutil.copytree(shipped, conf, ignore=shutil.ignore_patterns("__pycache__", "*.py"))
    (conf / "dataset" / "mine.yaml").write_text(
        (conf / "dataset" / "tiny.yaml").read_text().replace("name: tiny", "name: mine"))
    monkeypatch.setenv("POSERNET_CONFIG_DIR", str(conf))
    assert config_dir() == str(conf.resolve())
    assert "mine" in available_presets()
    assert load_preset("mine").name == "mine"
    monkeypatch.delenv("POSERNET_CONFIG_DIR")
    assert "mine" not in available_presets()


def _imported_modules(path: Path) -> set[str]:
    """Absolute names of the modules that the source file ``path`` imports."""
    package = list(path.relative_to(PACKAGE.parent).with_suffix("").parts[:-1])
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            name = ".".join([*base, *([node.module] if node.module else [])])
            found.add(name)
            found.update(f"{name}.{alias.name}" for alias in node.names)
    return found


def test_library_code_does_not_import_the_command_line_layer():
    """Only the commands import ``posernet.cli`` (the paper's experiments run ``posernet-train``
    as a subprocess); the library reads its configs from ``posernet.conf``."""
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.is_relative_to(PACKAGE / "cli"):
            continue
        bad = sorted(m for m in _imported_modules(path)
                     if m == "posernet.cli" or m.startswith("posernet.cli."))
        if bad:
            offenders[str(path.relative_to(PACKAGE))] = bad
    assert not offenders
    config = PACKAGE / "data" / "synthetic" / "config.py"
    assert "posernet.conf" in _imported_modules(config)
