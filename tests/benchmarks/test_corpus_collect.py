"""The corpus's file collector: pinned commits, unchanged copies, nothing overwritten (a throwaway git repository)."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "corpus"))

import collect  # noqa: E402  (a broken import must fail these tests, not skip them)

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(repo: Path, *args: str) -> str:
    result = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=True,
                            env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                                 "GIT_COMMITTER_EMAIL": "t@t", "PATH": "/usr/bin:/bin"})
    return result.stdout.strip()


@pytest.fixture
def upstream(tmp_path, monkeypatch):
    """A clone of ``owner/sample`` whose first commit holds two frames; a later commit changes one."""
    repo = tmp_path / "clones" / "sample"
    (repo / "data").mkdir(parents=True)
    _git(repo, "init", "-q")
    (repo / "data" / "f1.tif").write_bytes(b"one")
    (repo / "data" / "f2.tif").write_bytes(b"two")
    (repo / "data" / "notes.txt").write_text("not a frame")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "frames")
    pinned = _git(repo, "rev-parse", "HEAD")
    (repo / "data" / "f1.tif").write_bytes(b"changed later")
    _git(repo, "commit", "-q", "-am", "later")
    monkeypatch.setattr(collect, "EXTRA", tmp_path / "extra")
    monkeypatch.setattr(collect, "SOURCES", {"a-set": ("owner/sample", pinned, [("data/f*.tif", "frames")])})
    return tmp_path


def test_files_are_copied_from_the_pinned_commit_and_identical_ones_left_alone(upstream):
    assert collect.collect("a-set", upstream / "clones") == 2
    frames = upstream / "extra" / "a-set" / "frames"
    assert sorted(p.name for p in frames.iterdir()) == ["f1.tif", "f2.tif"]
    assert (frames / "f1.tif").read_bytes() == b"one"          # the pinned commit's, not the newest
    assert collect.collect("a-set", upstream / "clones") == 0  # a second run writes nothing


def test_a_differing_file_is_an_error_and_stays_as_it_was(upstream):
    frames = upstream / "extra" / "a-set" / "frames"
    frames.mkdir(parents=True)
    (frames / "f2.tif").write_bytes(b"someone else's")
    with pytest.raises(SystemExit, match="f2.tif: exists and differs"):
        collect.collect("a-set", upstream / "clones")
    assert (frames / "f2.tif").read_bytes() == b"someone else's"


def test_a_missing_clone_names_the_repository_and_the_fix(tmp_path, monkeypatch):
    monkeypatch.setattr(collect, "SOURCES", {"a-set": ("owner/absent", "0" * 40, [("x", ".")])})
    with pytest.raises(SystemExit, match=r"no clone of owner/absent.*git clone https://github.com/owner/absent"):
        collect.collect("a-set", tmp_path)


def test_every_set_outside_shared_has_its_table_beside_its_manifest():
    corpus = Path(collect.__file__).resolve().parent
    for name in collect.SOURCES:
        table = corpus / name / "illumination.csv"
        assert table.is_file(), table
        header = table.read_text().splitlines()[0].split(",")
        assert {"kx_norm", "ky_norm"} <= set(header), table
