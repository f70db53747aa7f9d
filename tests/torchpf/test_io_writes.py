"""torchpf.io writers: stale temporaries of killed writers are cleaned, the row-by-row CSV writer."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from torchpf import io as tio
from torchpf.io import MocapCsvWriter, clean_stale_temporaries, read_mocap_csv, write_atomic, write_mocap_csv


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_temporaries_are_cleaned_at_the_next_write(tmp_path, monkeypatch):
    dead = tmp_path / f".tmp-{_dead_pid()}-abc123track.csv"
    alive = tmp_path / f".tmp-{os.getppid()}-def456track.csv"  # a live writer's file is kept
    legacy_old = tmp_path / ".tmp-k2j3h4track.csv"
    legacy_new = tmp_path / ".tmp-zz99yytrack.csv"
    for f in (dead, alive, legacy_old, legacy_new):
        f.write_text("half a file")
    old = time.time() - 2 * 3600
    os.utime(legacy_old, (old, old))
    monkeypatch.setattr(tio, "_last_clean", {})
    write_atomic(tmp_path / "track.csv", "x\n")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([alive.name, legacy_new.name, "track.csv"])
    day_old = time.time() - 2 * 24 * 3600
    os.utime(alive, (day_old, day_old))  # pids are reused: a day-old temporary is stale whatever its pid
    assert clean_stale_temporaries(tmp_path) == [str(alive)]


def test_killed_writer_leaves_a_temporary_that_the_next_write_removes(tmp_path, monkeypatch):
    code = (
        "import os, sys, tempfile\n"
        f"fd, p = tempfile.mkstemp(dir={str(tmp_path)!r}, prefix=f'.tmp-{{os.getpid()}}-', suffix='a.bin')\n"
        "os.write(fd, b'x' * 1000)\n"
        "os.kill(os.getpid(), 9)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=False)
    assert any(p.name.startswith(".tmp-") for p in tmp_path.iterdir())
    monkeypatch.setattr(tio, "_last_clean", {})
    write_atomic(tmp_path / "a.bin", b"done")
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_csv_writer_rows_match_write_mocap_csv(tmp_path):
    values = np.random.default_rng(0).normal(size=(7, 3))
    names = ["a", "b", "c"]
    write_mocap_csv(tmp_path / "ref.csv", names, values, times=np.arange(7) / 25.0)
    with MocapCsvWriter(tmp_path / "out.csv", names, fps=25.0) as out:
        out.write(values[0])
        out.write(values[1:4])
        assert (tmp_path / "out.csv.partial").is_file() and not (tmp_path / "out.csv").exists()
        out.write(values[4:])
    assert (tmp_path / "out.csv").read_text() == (tmp_path / "ref.csv").read_text()
    assert not (tmp_path / "out.csv.partial").exists()


def test_csv_writer_keeps_finished_rows_on_error(tmp_path):
    values = np.ones((3, 2))
    with pytest.raises(RuntimeError), MocapCsvWriter(tmp_path / "out.csv", ["a", "b"], fps=10) as out:
        out.write(values)
        raise RuntimeError("crash")
    assert not (tmp_path / "out.csv").exists()
    names, times, got = read_mocap_csv(tmp_path / "out.csv.partial")
    assert names == ["a", "b"] and np.array_equal(got, values) and np.allclose(times, [0, 0.1, 0.2])
    with MocapCsvWriter(tmp_path / "n.csv", ["a"]) as out, pytest.raises(ValueError, match=r"values\[1, 0\]"):
        out.write([[1.0], [np.nan]])


@pytest.mark.skipif(not hasattr(os, "fchmod"), reason="POSIX permission bits")
def test_written_files_get_the_usual_permissions(tmp_path):
    from tests.priors.test_action import tiny_model
    from torchpf.camera import camera_ring, save_cameras

    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "a.bin", b"x")  # mkstemp alone would leave 0600
        write_mocap_csv(tmp_path / "m.csv", ["a"], np.zeros((2, 1)))
        save_cameras(tmp_path / "cameras.yaml", camera_ring(2))
        tiny_model().save(tmp_path / "walk.npz")
        with MocapCsvWriter(tmp_path / "w.csv", ["a"]) as out:
            out.write(np.zeros(1))
        for name in ("a.bin", "m.csv", "cameras.yaml", "walk.npz", "w.csv"):
            assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name
        os.umask(0o077)  # a private umask is honoured
        write_atomic(tmp_path / "b.bin", b"x")
        assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)
    (tmp_path / "a.bin").chmod(0o640)  # rewriting keeps a file's own permissions, as open(..., "w") does
    write_atomic(tmp_path / "a.bin", b"y")
    assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o640
