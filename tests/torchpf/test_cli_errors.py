"""One-line errors, Ctrl-C, --threads and output checks of the command lines (torchpf.cli)."""

import argparse
import signal
import subprocess
import sys

import pytest
import torch

from torchpf import Skeleton, cli
from torchpf.__main__ import main
from torchpf.assets import path
from training.__main__ import main as training_main

URDF = str(path("human.urdf"))


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "error:" in err, err
    for w in words:
        assert w in err, err
    return err


def test_default_threads(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    assert cli.default_threads() >= 1
    monkeypatch.setenv("CI", "true")
    assert cli.default_threads() == 1


@pytest.mark.parametrize(
    ("error", "words"),
    [
        (MemoryError(), "out of memory"),
        (OverflowError("cannot convert float infinity to integer"), "OverflowError: cannot convert"),
        (
            RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 99 bytes"),
            "99 bytes",
        ),
        (RecursionError("maximum recursion depth exceeded"), "nested too deeply"),
        (FileNotFoundError(2, "No such file or directory", "x.csv"), "x.csv: No such file"),
    ],
)
def test_run_command_turns_known_errors_into_one_line(capsys, monkeypatch, error, words):
    monkeypatch.delenv(cli.DEBUG_ENV, raising=False)

    def boom(args):
        raise error

    args = argparse.Namespace(command="cmd", threads=1, debug=False)
    assert cli.run_command("prog", args, boom) == 2
    _one_line_error(capsys, "prog cmd: error:", words)
    with pytest.raises(type(error)):
        cli.run_command("prog", argparse.Namespace(command="cmd", threads=1, debug=True), boom)
    monkeypatch.setenv(cli.DEBUG_ENV, "1")
    with pytest.raises(type(error)):
        cli.run_command("prog", args, boom)


def test_run_command_interrupt_and_bugs(capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    def bug(args):
        raise KeyError("a bug shows its traceback")

    args = argparse.Namespace(command="cmd", threads=2, debug=False)
    assert cli.run_command("prog", args, interrupted) == 130
    assert capsys.readouterr().err.strip() == "prog cmd: interrupted"
    assert torch.get_num_threads() == 2
    with pytest.raises(KeyError):
        cli.run_command("prog", args, bug)


def test_outputs_are_checked_before_the_run(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    for out, words in [(tmp_path, "is a directory"), (tmp_path / "file" / "t.csv", "is not a directory")]:
        # the sequence does not exist: the output check comes first
        assert main(["track", str(tmp_path / "nowhere"), "--skeleton", URDF, "--out", str(out)]) == 2
        _one_line_error(capsys, "--out", words)
    assert (
        training_main(
            ["fit-dynamics", "x.csv", "--skeleton", URDF, "--out", str(tmp_path / "file" / "d.npz")]
        )
        == 2
    )
    _one_line_error(capsys, "is not a directory")
    assert training_main(["convert", "x.bvh", "--out-dir", str(tmp_path / "file")]) == 2
    _one_line_error(capsys, "--out-dir", "not a directory")


def test_track_refuses_bad_config_particles_and_threshold(seq_dir, tmp_path, capsys):
    out = str(tmp_path / "t.csv")
    config = tmp_path / "config.yaml"
    config.write_text("n_particle: 100\nfilter: sir\n")
    assert main(["track", str(seq_dir), "--skeleton", URDF, "--out", out, "--config", str(config)]) == 2
    _one_line_error(capsys, "config.yaml: unknown key(s) ['n_particle']")
    assert main(["track", str(seq_dir), "--skeleton", URDF, "--out", out, "--particles", "3000000000"]) == 2
    _one_line_error(capsys, "--particles 3000000000 needs about", "GiB of memory")
    track = seq_dir / "truth.csv"
    argv = ["evaluate", str(track), "--truth", str(track), "--skeleton", URDF, "--threshold", "-1"]
    assert main(argv) == 2
    _one_line_error(capsys, "--threshold must be a positive number")
    empty = tmp_path / "empty.csv"
    empty.write_text(",".join(Skeleton.from_urdf(URDF).dof_names) + "\n")
    assert main(["evaluate", str(empty), "--truth", str(empty), "--skeleton", URDF]) == 2
    _one_line_error(capsys, "empty.csv: no frames to evaluate")


def test_unreadable_inputs_name_the_file(seq_dir, tmp_path, capsys):
    bad = tmp_path / "latin.urdf"
    bad.write_bytes(b"<robot name='\xe9'/>")
    assert main(["evaluate", "t.csv", "--truth", "t.csv", "--skeleton", str(bad)]) == 2
    _one_line_error(capsys, "latin.urdf: not a UTF-8")
    seq = tmp_path / "seq"
    seq.mkdir()
    cams = (seq_dir / "cameras.yaml").read_text()
    for text, words in [
        (cams.replace("width: 64", "width: .inf", 1), "key 'width' must be a positive integer"),
        (
            "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: [",
            "not valid FileStorage YAML",
        ),
        ("%YAML:1.0\n---\ncamera_matrix: [1, 0, 0]\nimage_width: .inf\nimage_height: 3\n", "cameras.yaml"),
    ]:
        (seq / "cameras.yaml").write_text(text)
        assert main(["track", str(seq), "--skeleton", URDF, "--out", str(tmp_path / "t.csv")]) == 2
        _one_line_error(capsys, "cameras.yaml", words)
    (seq / "cameras.yaml").write_bytes(b"cameras: {\xff}")
    assert main(["track", str(seq), "--skeleton", URDF, "--out", str(tmp_path / "t.csv")]) == 2
    _one_line_error(capsys, "cameras.yaml: not UTF-8")


def test_ctrl_c_prints_interrupted_and_exits_130(seq_dir, tmp_path):
    argv = [sys.executable, "-m", "torchpf", "track", str(seq_dir), "--skeleton", URDF, "--out"]
    proc = subprocess.Popen(
        [*argv, str(tmp_path / "t.csv"), "--particles", "50000", "--threads", "1"],
        stderr=subprocess.PIPE,
        text=True,
        # a test runner's worker may ignore SIGINT, and a child inherits that (Python then installs no
        # KeyboardInterrupt handler): give the CLI the disposition a terminal user's process has
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    proc.stderr.read(1)  # the progress bar: the run has started
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and err.strip().endswith("python -m torchpf track: interrupted"), err
    assert "Traceback" not in err


def test_threads_option_in_every_command():
    for prog, commands in [("torchpf", ["track", "evaluate", "calibrate"]), ("training", ["convert", "fit"])]:
        for command in commands:
            res = subprocess.run(
                [sys.executable, "-m", prog, command, "--help"], capture_output=True, text=True
            )
            assert res.returncode == 0 and "--threads" in res.stdout and "--debug" in res.stdout
