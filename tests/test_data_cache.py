"""warpgs/data/cache.py: where derived files are cached, and publishing a folder into the cache whole."""
import os

from warpgs.data.cache import cache_dir, publish_folder


def test_cache_dir_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c"


def test_a_published_entry_is_whole_and_the_first_one_stays(tmp_path):
    made = tmp_path / "made"
    (made / "sub").mkdir(parents=True)
    (made / "a.txt").write_text("first")
    (made / "sub" / "b.txt").write_text("b")
    entry = tmp_path / "cache" / "kind" / "key"
    publish_folder(made, entry)
    assert (entry / "a.txt").read_text() == "first" and (entry / "sub" / "b.txt").read_text() == "b"
    (made / "a.txt").write_text("second")  # a later run with the same key does not replace what is there
    publish_folder(made, entry)
    assert (entry / "a.txt").read_text() == "first"
    assert sorted(os.listdir(entry.parent)) == ["key"]  # no temporary copy left behind


def test_an_unwritable_cache_costs_only_a_line(tmp_path, capsys):
    made = tmp_path / "made"
    made.mkdir()
    (made / "a.txt").write_text("x")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    publish_folder(made, blocker / "key", what="depth priors")  # its parent is a file: nothing can be made there
    assert "depth priors: could not cache them in" in capsys.readouterr().err
