"""The config check every posernet-* command runs first (posernet.cli.validation) and the shared
error policy (posernet.cli.common): in-process, fast. The commands themselves, as subprocesses,
are in test_failures.py."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from posernet.cli import CONFIG_DIR
from posernet.cli.common import hydra_error_message, preflight, run_task
from posernet.cli.validation import COMMANDS, ConfigValueError, check_config
from posernet.io import writable_dir, writable_file

REQUIRED = {  # the values a command cannot run without (??? in its config)
    "train": [], "eval": ["ckpt_path=x.ckpt"], "refine": ["input=x.json"], "demo": [],
    "reconstruct": ["images=photos", "intrinsics='1,1,1,1'"], "make_data": [],
}


def cfg_of(command: str, *overrides: str, tmp: Path | None = None):
    outs = {"train": "out_dir", "eval": "out_dir", "refine": "output", "demo": "out_dir",
            "reconstruct": "out_dir", "make_data": "out_dir"}
    given = [*REQUIRED[command], *overrides]
    if tmp is not None and not any(o.startswith(outs[command] + "=") for o in given):
        given.append(f"{outs[command]}={tmp / 'out'}")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(command, overrides=given)


# ------------------------------------------------------------------------- the shipped configs


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_default_configs_pass(command, tmp_path):
    check_config(cfg_of(command, tmp=tmp_path), command)
    assert not (tmp_path / "out").exists()  # checked, not created


def _choices(group: str) -> list[str]:
    return sorted(p.stem for p in (Path(CONFIG_DIR) / group).glob("*.yaml"))


@pytest.mark.parametrize(("command", "group", "option"), [
    *[("train", g, o) for g in ("model", "data", "sync", "callbacks") for o in _choices(g)],
    *[("train", "trainer", "cpu")],
    *[("train", "+experiment", o) for o in _choices("experiment")],
    *[("reconstruct", g, o) for g in ("proposals", "matcher", "box_matching", "relpose", "sync")
      for o in _choices(g)],
    *[("make_data", "dataset", o) for o in _choices("dataset")],
])
def test_every_shipped_group_option_passes(command, group, option, tmp_path):
    if option == "gtsam":
        pytest.importorskip("gtsam")
    extra = ["proposals.path=boxes.json"] if option == "file" else []
    if option == "learned":  # needs its trained network: a clear line without one
        with pytest.raises(ConfigValueError, match=r"^sync.ckpt_path: a value is required"):
            check_config(cfg_of(command, f"{group}={option}", tmp=tmp_path), command)
        import torch

        from posernet.lit.learned_sync_module import LearnedSyncModule

        module = LearnedSyncModule()
        ckpt = tmp_path / "sync.ckpt"
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                    "posernet": {"tag": module.CHECKPOINT_TAG}}, ckpt)
        extra = [f"sync.ckpt_path={ckpt}"]
    check_config(cfg_of(command, f"{group}={option}", *extra, tmp=tmp_path), command)


# ------------------------------------------------------------------------- bad values

BAD = [
    # the three the issue starts from: a clear line instead of a late traceback
    ("train", "model.net.depth=abc", "model.net.depth: 'abc' is not an integer >= 1"),
    ("train", "model.net.depth=2.5", "model.net.depth: 2.5 is not an integer >= 1"),
    ("train", "model.loss.alpha=abc", "model.loss.alpha: 'abc' is not a number >= 0"),
    ("train", "model.optimizer.lr=0", "model.optimizer.lr: 0 is not a number > 0"),
    ("train", "model.loss.harm_scale=-1", "model.loss.harm_scale: -1 is not a number >= 0"),
    ("train", "model.loss.harm=abc", "model.loss.harm: 'abc' is not a number >= 0"),
    ("train", "model.scheduler.factor=1.5",
     r"model.scheduler.factor: 1.5 is not a number in \(0, 1\)"),
    ("train", "model.net.residual=maybe", "model.net.residual: 'maybe' is not true or false"),
    ("train", "data.batch_size=0", "data.batch_size: 0 is not an integer >= 1"),
    ("train", "data.root=[]", r"data.root: \[\] is not a path or a list of paths"),
    ("train", "data.root=[a,3.5]", "data.root: .* is not a path or a list of paths"),
    ("train", "data.estimate=xx", "data.estimate: 'xx' is not one of kp, bb"),
    ("train", "data.size=huge", "data.size: 'huge' is not one of small, large"),
    ("train", "num_threads=0", "num_threads: 0 is not an integer >= 1 or null"),
    ("train", "seed=-1", "seed: -1 is not an integer >= 0"),
    ("train", "trainer.max_epochs=ten",
     "trainer.max_epochs: 'ten' is not an integer >= 1 \\(or -1: no limit\\) or null"),
    ("train", "trainer.accelerator=gpx", "trainer.accelerator: 'gpx' is not one of auto, cpu"),
    ("train", "test_after_training=1", "test_after_training: 1 is not true or false"),
    ("eval", "estimate=xx", "estimate: 'xx' is not one of kp, bb, free, gt or null"),
    ("eval", "digits=-1", r"digits: -1 is not an integer in \[0, 12\]"),
    ("eval", "ckpt_path=null", "ckpt_path: None is not a path"),
    ("refine", "device=gpu", "device: 'gpu' is not one of cpu, cuda, cuda:N, auto"),
    ("refine", "strict=yes", "strict: 'yes' is not true or false"),
    ("refine", "sync.scale=bogus", "sync.scale: 'bogus' is not one of unit, given, oracle, free"),
    ("refine", "sync.max_iters=0", "sync.max_iters: 0 is not an integer >= 1"),
    ("refine", "sync.scale=free", "sync=eig_se3: scale='free' is not supported"),  # backend's
    ("demo", "estimate=free", "estimate: 'free' is not one of kp, bb"),
    ("demo", "images.frames=1", "images.frames: 1 is not an integer >= 2"),
    ("demo", "images.matcher=orb", "images.matcher: 'orb' is not one of auto, sift"),
    ("demo", "images.scene=garage", "images.scene: 'garage' is not one of chess"),
    ("demo", "dataset.small.graph_size=1", "dataset.small.graph_size"),  # the options' own
    ("reconstruct", "workers=-1", "workers: -1 is not an integer >= 0"),
    ("reconstruct", "proposals.top_k=abc", "proposals.top_k: 'abc' is not an integer >= 1"),
    ("reconstruct", "proposals.max_area=2", r"proposals.max_area: 2 is not a number in \(0, 1\]"),
    ("reconstruct", "box_matching.min_keypoints=0",
     "box_matching.min_keypoints: 0 is not an integer >= 1"),
    ("reconstruct", "relpose.method=lmeds", "relpose.method: 'lmeds' is not one of usac, ransac"),
    ("reconstruct", "matcher=sift matcher.ratio=0",
     r"matcher.ratio: 0 is not a number in \(0, 1\]"),
    ("reconstruct", "proposals=file", r"proposals.path: a value is required"),
    ("make_data", "source=flickr", "source: 'flickr' is not one of synthetic, sevenscenes"),
    ("make_data", "workers=abc", "workers: 'abc' is not an integer >= 1"),
    ("make_data", "source=sevenscenes frame_step=0", "frame_step: 0 is not an integer >= 1"),
    ("make_data", "source=sevenscenes matcher=sift matcher.max_features=-5",
     "matcher.max_features: -5 is not an integer >= 1"),
    # types taken from the target's own signature or options dataclass (no rule written here)
    ("refine", "sync=rotation_translation sync.triangle_weights=3",
     "sync.triangle_weights: 3 is not true or false"),
    ("reconstruct", "matcher=sift matcher.mutual=often", "matcher.mutual: 'often' is not true"),
    ("train", "data.shuffle=sometimes", "data.shuffle: 'sometimes' is not true or false"),
    # a value where a group of options belongs
    ("reconstruct", "pairs=exhaustive",
     r"pairs: 'exhaustive' is not a group of options; did you mean pairs.mode=exhaustive\?"),
    ("reconstruct", "bundle=3", r"bundle: 3 is not a group of options; set its options as "
                                r"bundle.<option>=..."),
]


@pytest.mark.parametrize(("command", "overrides", "message"), BAD)
def test_bad_value_is_one_line_naming_key_value_and_expectation(command, overrides, message,
                                                                tmp_path):
    cfg = cfg_of(command, *overrides.split(), tmp=tmp_path)
    with pytest.raises(ValueError, match=message) as info:
        check_config(cfg, command)
    assert "\n" not in str(info.value)


def test_front_end_is_checked_only_for_images(tmp_path):
    # synthetic data never builds the front end: its options do not matter there
    check_config(cfg_of("make_data", "proposals=file", tmp=tmp_path), "make_data")


def test_required_value(tmp_path):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("refine", overrides=[f"output={tmp_path}/r.json"])
    with pytest.raises(ConfigValueError, match=r"^input: a value is required \(input=<a path>\)"):
        check_config(cfg, "refine")


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
@pytest.mark.parametrize(("command", "override", "message"), [
    ("eval", "device=cuda", "device=cuda but CUDA is not available"),
    ("refine", "device=cuda:1", "device=cuda:1 but CUDA is not available"),
    ("demo", "device=cuda", "device=cuda but CUDA is not available"),
    ("reconstruct", "device=cuda", "device=cuda but CUDA is not available"),
    ("train", "trainer=gpu", "trainer.accelerator=gpu but CUDA is not available"),
])
def test_cuda_without_cuda(command, override, message, tmp_path):
    with pytest.raises(ConfigValueError, match=f"^{message}$"):
        check_config(cfg_of(command, override, tmp=tmp_path), command)


# ------------------------------------------------------------------------- output paths


def test_writable_dir_creates_nothing(tmp_path):
    target = tmp_path / "a" / "b"
    assert writable_dir(target) == target
    assert list(tmp_path.iterdir()) == []


def test_unwritable_outputs_name_the_users_path(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigValueError, match=r"^out_dir: '.*/file/sub' is not a writable "
                                               r"folder \(.*/file is not a folder\)$"):
        writable_dir(tmp_path / "file" / "sub")
    with pytest.raises(ConfigValueError, match=r"^out_dir: '/proc/nope/x' is not a writable "
                                               r"folder \(cannot write in /proc"):
        writable_dir("/proc/nope/x")
    with pytest.raises(ConfigValueError, match=r"^output: '/proc/x/r.json' is not a writable "
                                               r"file \(cannot write in /proc"):
        writable_file("/proc/x/r.json")
    with pytest.raises(ConfigValueError, match=r"is not a writable file \(it is a folder\)"):
        writable_file(tmp_path, "output")


# ------------------------------------------------------------------------- commands check first


def test_task_functions_check_before_writing(tmp_path):
    """The Python entry points (what Hydra calls) check the config before any output."""
    from posernet.cli.demo import demo
    from posernet.cli.evaluate import evaluate
    from posernet.cli.make_data import run as make_data
    from posernet.cli.reconstruct import run as reconstruct
    from posernet.cli.refine import refine
    from posernet.cli.train import train

    out = tmp_path / "out"
    for fn, command, bad in ((train, "train", "model.net.depth=abc"), (evaluate, "eval", "seed=x"),
                             (refine, "refine", "batch_size=0"), (demo, "demo", "workers=0"),
                             (reconstruct, "reconstruct", "pictures=-1"),
                             (make_data, "make_data", "seed=x")):
        cfg = cfg_of(command, bad, tmp=tmp_path)
        with pytest.raises(ConfigValueError):
            fn(cfg)
        assert not out.exists(), command


def test_make_data_execute_exits_1(tmp_path, capsys):
    from posernet.cli.make_data import execute

    assert execute(cfg_of("make_data", "dataset=tiny", "workers=0", tmp=tmp_path)) == 1
    assert capsys.readouterr().err == (
        "posernet-make-data: error: workers: 0 is not an integer >= 1\n")


# ------------------------------------------------------------------------- preflight (main())


@pytest.mark.parametrize(("argv", "message"), [
    (["model.net.depth=abc"], "model.net.depth: 'abc' is not an integer >= 1"),
    (["model.depth=3"], "model.depth: no such key in this command's config"),
    (["sync=nope"], "sync: 'nope' is not one of eig_se3, gtsam, learned, none, "
                   "rotation_translation"),
    (["model.dept=3"], "model.dept: no such key in this command's config"),
    (["device=cuda"], "device: no such key in this command's config (the trainer picks it"),
    (["hydra.run.dir=/proc/posernet-run"], "hydra.run.dir: '/proc/posernet-run' is not a "
                                            "writable folder"),
])
def test_preflight_reports_before_hydra_makes_a_run_folder(argv, message, tmp_path, capsys,
                                                           monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = [*argv] if any(a.startswith("hydra.") for a in argv) else \
        [*argv, f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as exc:
        preflight("posernet-train", "train", argv)
    assert exc.value.code == 1
    err = capsys.readouterr().err
    assert err.startswith(f"posernet-train: error: {message}") and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [["--help"], ["--cfg", "job"], ["-m", "model.net.depth=2,3"]])
def test_preflight_leaves_hydras_own_modes_alone(argv):
    preflight("posernet-train", "train", argv)  # no exit: Hydra handles these


def test_preflight_passes_a_good_command_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    preflight("posernet-refine", "refine", ["input=x.json"])
    assert list(tmp_path.iterdir()) == []


def test_hydra_error_message_of_a_bad_override():
    from hydra.errors import OverrideParseException

    msg = hydra_error_message(OverrideParseException("a\nb", "no viable alternative"))
    assert "\n" not in msg


# ------------------------------------------------------------------------- run_task


def test_run_task_policy(capsys):
    def user_error(cfg):
        raise FileNotFoundError("input graph file not found: x.pt")

    def ctrl_c(cfg):
        raise KeyboardInterrupt

    with pytest.raises(SystemExit) as exc:
        run_task("posernet-x", user_error, None)
    assert exc.value.code == 1
    assert capsys.readouterr().err == "posernet-x: error: input graph file not found: x.pt\n"
    with pytest.raises(SystemExit) as exc:
        run_task("posernet-x", ctrl_c, None, resume_hint=lambda cfg: "resume=true finishes it")
    assert exc.value.code == 130
    assert capsys.readouterr().err == "posernet-x: interrupted; resume=true finishes it\n"

    def bug(cfg):
        raise RuntimeError("bug")

    with pytest.raises(RuntimeError):  # a bug stays a traceback
        run_task("posernet-x", bug, None)


def test_lightning_exit_after_ctrl_c_is_an_interruption(capsys, monkeypatch):
    """Lightning catches Ctrl-C itself and calls sys.exit(1): still exit status 130."""
    import posernet.cli.common as common

    def fit(cfg):
        common._on_sigint(signal.SIGINT, None)

    def lightning_fit(cfg):
        try:
            fit(cfg)
        except KeyboardInterrupt:
            raise SystemExit(1) from None

    monkeypatch.setattr(common, "_sigint_seen", False)
    with pytest.raises(SystemExit) as exc:
        run_task("posernet-train", lightning_fit, None)
    assert exc.value.code == 130
    assert capsys.readouterr().err == "posernet-train: interrupted\n"


def test_ctrl_c_while_a_command_imports_is_one_line():
    """A command spends its first second or more importing torch & co., before run_app sets up
    its Ctrl-C handling: a Ctrl-C then is still one line and exit status 130, not a traceback
    from inside an import. Only in a posernet-* command: a program importing posernet keeps
    Python's own handling."""
    import subprocess

    from posernet import startup

    script = ("import os, signal, sys, threading\n"
              "sys.argv[0] = {prog!r}\n"
              "threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
              "import posernet, time\n"
              "time.sleep(30)\n")
    from helpers import as_from_a_terminal

    r = subprocess.run([sys.executable, "-c", script.format(prog="/venv/bin/posernet-x")],
                       capture_output=True, text=True, timeout=120,
                       preexec_fn=as_from_a_terminal)
    assert (r.returncode, r.stderr) == (130, "posernet-x: interrupted\n")
    # another program importing posernet keeps Python's own handler (what a Ctrl-C does
    # inside a third-party import then is that library's business: checked without a signal)
    probe = ("import signal, sys\n"
             "sys.argv[0] = 'my-tool'\n"
             "import posernet\n"
             "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)\n")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                       timeout=120)
    assert (r.returncode, r.stdout.strip()) == (0, "True"), r.stderr
    assert not startup.install()  # under pytest: not a command, nothing installed
    assert signal.getsignal(signal.SIGINT) is not startup.interrupted_while_starting


def test_multiline_messages_become_one_line(capsys):
    from omegaconf import OmegaConf
    from omegaconf.errors import MissingMandatoryValue

    cfg = OmegaConf.create({"input": "???"})
    with pytest.raises(MissingMandatoryValue) as exc:
        _ = cfg.input
    from posernet.cli.common import report_error

    report_error("posernet-x", exc.value)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "full_key" not in err


# ------------------------------------------------------------------------- --help


@pytest.mark.parametrize(("prog", "name"), [
    ("posernet-reconstruct", "reconstruct"), ("posernet-train", "train"),
    ("posernet-eval", "eval"), ("posernet-refine", "refine"),
    ("posernet-make-data", "make_data"), ("posernet-demo", "demo")])
def test_help_is_written_from_the_commands_own_config(prog, name):
    from posernet.cli import CONFIG_DIR
    from posernet.cli.help import command_help

    text = command_help(prog, CONFIG_DIR, name)
    assert text.startswith(f"usage: {prog}") and "options (key, default, meaning):" in text
    assert "???" not in text and "hydra.run" not in text
    if name == "reconstruct":
        assert text.splitlines()[0] == "usage: posernet-reconstruct images=... [key=value ...]"
        assert "\nrequired:\n  images" in text
        # only this command's groups, each with its choices, default first
        assert "  matcher                  sift_xfeat, auto, sift, xfeat, xfeat_lighterglue" in text
        assert "trainer" not in text and "callbacks" not in text
        # meanings from the comment beside an option, or the block right above it
        line = next(ln for ln in text.splitlines() if ln.strip().startswith("pairs.mode "))
        assert "exhaustive up to auto_max" in line
        line = next(ln for ln in text.splitlines() if ln.strip().startswith("boxes "))
        assert "only when a stage uses them" in line
    if name == "train":
        assert "  trainer" in text and "gpu" in text


@pytest.mark.parametrize(("prog", "name"), [
    ("posernet-reconstruct", "reconstruct"), ("posernet-train", "train"),
    ("posernet-eval", "eval"), ("posernet-refine", "refine"),
    ("posernet-make-data", "make_data"), ("posernet-demo", "demo")])
def test_help_lists_every_option_of_the_composed_config(prog, name):
    """--help lists each option of the command's composed config (its config groups' too),
    with the meaning written beside it in whichever file sets it."""
    from posernet.cli.help import command_help

    text = command_help(prog, CONFIG_DIR, name)
    listed = {ln.split()[0] for ln in text.split("options (key, default, meaning):\n")[1]
              .splitlines() if ln.startswith("  ")}
    required = {ln.split()[0] for block in text.split("\n\n") if block.startswith("required:")
                for ln in block.splitlines()[1:]}
    cfg = cfg_of(name)
    wanted = {k for k in _leaves(cfg) if not any(p.startswith("_") for p in k.split("."))}
    assert wanted - listed - required == set()
    if name == "train":
        lines = {ln.split()[0]: ln for ln in text.splitlines() if ln.startswith("  ")}
        for key in ("data.root", "trainer.max_epochs", "model.net.depth", "model.loss.alpha"):
            assert key in listed, key
        assert "message-passing rounds" in lines["model.net.depth"]
        assert "or a list of them" in lines["data.root"]  # a continued comment


def test_help_flag_prints_it_and_exits_0(capsys, monkeypatch):
    from posernet.cli.common import run_app

    monkeypatch.setattr(sys, "argv", ["posernet-reconstruct", "--help"])
    with pytest.raises(SystemExit) as exc:
        run_app("posernet-reconstruct", "reconstruct", lambda: pytest.fail("app ran"))
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("usage: posernet-reconstruct images=...")


def test_commands_skip_the_final_garbage_collection_once(monkeypatch):
    """Every command registers gc.freeze to run at interpreter exit (Python's final
    collections over torch's objects cost 0.3-0.45 s of a short run), once per process, and
    never freezes the collector while the process is still running."""
    import atexit
    import gc

    from posernet.cli import common

    registered = []
    monkeypatch.setattr(atexit, "register", lambda fn, *a, **k: registered.append(fn))
    monkeypatch.setattr(common, "_final_collection_skipped", False)
    monkeypatch.setattr(sys, "argv", ["posernet-reconstruct", "--help"])
    for _ in range(2):
        with pytest.raises(SystemExit):
            common.run_app("posernet-reconstruct", "reconstruct", lambda: None)
    assert registered == [gc.freeze]
    assert gc.get_freeze_count() == 0


def _leaves(node, prefix=""):
    """Dotted keys of the plain values of a yaml mapping."""
    from omegaconf import OmegaConf

    for k in node.keys():
        child = node._get_node(k)  # unresolved: ??? and ${...} values stay as they are
        if OmegaConf.is_dict(child):
            yield from _leaves(child, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}"


@pytest.mark.parametrize("group,files", [
    ("bundle", ["reconstruct.yaml:bundle"]), ("verify", ["reconstruct.yaml:verify"]),
    ("pairs", ["reconstruct.yaml:pairs"]), ("check", ["reconstruct.yaml:check"]),
    ("relpose", ["relpose/*.yaml"]), ("box_matching", ["box_matching/*.yaml"]),
    ("model", ["model/posernet.yaml", "model/adaptive.yaml", "model/residual.yaml",
               "model/posernet_large.yaml", "model/end_to_end.yaml"]),
    ("sync", ["sync/*.yaml"]), ("matcher", ["matcher/*.yaml"]),
    ("proposals", ["proposals/*.yaml"]), ("data", ["data/*.yaml"]),
    ("trainer", ["trainer/*.yaml"]), ("images", ["demo.yaml:images"]),
])
def test_every_shipped_option_has_a_rule(group, files):
    """No option of a shipped config goes unchecked: each group's rules are its declaring
    dataclass's fields (:func:`posernet.cli.validation.group_rules`), so adding an option to a
    dataclass, and to its yaml, needs no second edit here."""
    from omegaconf import OmegaConf

    from posernet.cli.validation import group_rules

    command = {"model": "train", "data": "train", "trainer": "train", "images": "demo"}
    spec = COMMANDS[command.get(group, "reconstruct")].groups[group]
    missing = []
    for f in files:
        name, _, key = f.partition(":")
        for path in sorted(Path(CONFIG_DIR).glob(name)):
            node = OmegaConf.load(path)
            node = node[key] if key else node
            # a group built from its _target_ takes its keys from that target
            schema = group_rules(spec, OmegaConf.create({group: node}))
            missing += [f"{path.name}: {k}" for k in _leaves(node)
                        if not k.startswith(("_", "defaults")) and k not in schema]
    assert not missing, missing


def test_a_target_without_options_is_checked_against_its_annotations():
    from posernet.options import signature_rules

    class Target:
        def __init__(self, n: int = 1, x: float | None = None, flag: bool = True,
                     name: str = "a", **extra: object) -> None:
            pass

    s = signature_rules(Target)
    assert set(s) == {"n", "x", "flag", "name"}
    assert s["n"].ok(3) and not s["n"].ok(2.5)
    assert s["x"].ok(None) and s["x"].ok(1.5) and not s["x"].ok("1.5")
    assert s["flag"].ok(False) and not s["flag"].ok(1)
    assert s["name"].ok("b") and not s["name"].ok(3)


@pytest.mark.parametrize("group", ["sync", "matcher", "proposals", "data", "relpose",
                                   "box_matching", "trainer"])
def test_every_shipped_target_declares_its_options(group):
    """Every shipped group built from a ``_target_`` declares its options on a dataclass (the
    target itself or its ``Options``), so that their ranges, choices and help live there."""
    import dataclasses

    from hydra.utils import get_object
    from omegaconf import OmegaConf

    undeclared = []
    for path in sorted(Path(CONFIG_DIR).glob(f"{group}/*.yaml")):
        node = OmegaConf.load(path)
        target = node.get("_target_")
        if target is None or not set(node) - {"_target_", "name"}:  # a variant; no options
            continue
        owner = get_object(str(target))
        if not dataclasses.is_dataclass(getattr(owner, "Options", owner)):
            undeclared.append(f"{path.name}: {target}")
    assert not undeclared, undeclared
