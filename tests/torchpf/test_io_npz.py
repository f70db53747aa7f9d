"""torchpf.io.read_versioned_npz: the one reader of the library's versioned .npz files."""

import json

import numpy as np
import pytest

from torchpf.io import read_npz, read_versioned_npz


class FormatError(ValueError):
    pass


def _write(path, meta, **arrays):
    np.savez(path, metadata=np.array(json.dumps(meta)), **arrays)


def test_reads_arrays_metadata_and_version(tmp_path):
    f = tmp_path / "ok.npz"
    _write(f, {"format": "thing", "version": 2, "name": "x"}, a=np.arange(3.0))
    data, meta, version = read_versioned_npz(f, "thing", 2, "thing", FormatError)
    assert version == 2 and meta["name"] == "x" and np.array_equal(data["a"], np.arange(3.0))


@pytest.mark.parametrize(
    ("meta", "message"),
    [
        ({"format": "other", "version": 1}, "not an action-model file"),
        ({"format": "thing", "version": 3}, "newer than this torchpf reads"),
        ({"format": "thing", "version": True}, "bad format version"),
        ({"format": "thing", "version": 0}, "bad format version"),
    ],
)
def test_bad_metadata_names_the_file(tmp_path, meta, message):
    f = tmp_path / "bad.npz"
    _write(f, meta)
    with pytest.raises(FormatError, match=rf"bad\.npz: .*{message}"):
        read_versioned_npz(f, "thing", 2, "action-model", FormatError)


def test_missing_file_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"action model file not found: .*nowhere\.npz"):
        read_versioned_npz(tmp_path / "nowhere.npz", "thing", 1, "action-model", FormatError)


def test_not_a_zip_and_no_metadata(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(FormatError, match="junk.npz: not a readable thing .npz file"):
        read_versioned_npz(junk, "thing", 1, "thing", FormatError)
    bare = tmp_path / "bare.npz"
    np.savez(bare, a=np.zeros(2))
    with pytest.raises(FormatError, match="no 'metadata' entry"):
        read_versioned_npz(bare, "thing", 1, "thing", FormatError)


def _mutated(path, old: bytes, new: bytes):
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))


def test_read_npz_checks_sizes_before_allocating(tmp_path):
    f = tmp_path / "huge.npz"
    np.savez(f, a=np.zeros(8192))  # > one zip read chunk: the CRC is checked only at the member's end
    _mutated(f, b"(8192,), }" + b" " * 12, b"(81920000000000,), }" + b"  ")  # same header length
    with pytest.raises(FormatError, match="huge.npz: .*declares shape"):
        read_npz(f, "thing", FormatError)
    np.savez(f, a=np.zeros(8))
    _mutated(f, b"'shape': (8,), }", b"'shape': (99999999999999,)")
    with pytest.raises(FormatError, match="huge.npz"):  # the header length no longer fits: any clear error
        read_npz(f, "thing", FormatError)


@pytest.mark.parametrize(
    ("old", "new"),
    [(b"'descr'", b"'descr\x00"), (b"PK\x03\x04", b"PK\x03\x05"), (b"\x00\x00\x00\x00", b"\x63\x00\x00\x00")],
)
def test_read_npz_mutations_are_clear_errors(tmp_path, old, new):
    f = tmp_path / "m.npz"
    np.savez(f, a=np.arange(4.0))
    _mutated(f, old, new)
    try:
        data = read_npz(f, "thing", FormatError)
    except FormatError as e:
        assert "m.npz" in str(e)
    else:
        assert set(data) == {"a"}


def test_keypoints_npz_errors_name_the_file(tmp_path):
    from torchpf.camera import Camera, save_cameras
    from torchpf.sequence import read_sequence

    cam = Camera(
        np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]]), np.eye(3), [0, 0, 3], width=160, height=120
    )
    save_cameras(tmp_path / "cameras.yaml", [cam])
    (tmp_path / "keypoints.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ValueError, match="keypoints.npz: not a readable keypoints .npz file"):
        read_sequence(tmp_path)
    np.savez(tmp_path / "keypoints.npz", uv=np.full((2, 1, 3, 2), np.inf), joints=np.array(["a", "b", "c"]))
    with pytest.raises(ValueError, match="keypoints.npz: 'uv' holds infinite values"):
        read_sequence(tmp_path)
