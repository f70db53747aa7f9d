"""torchpf.io.read_versioned_npz: the one reader of the library's versioned .npz files."""

import json

import numpy as np
import pytest

from torchpf.io import read_versioned_npz


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
