"""warpgs/data/cache.py: where derived files are cached, publishing a folder into the cache whole, and
`warpgs-cache` (warpgs/cli/cache.py): listing the entries, dropping the least recently used, clearing kinds."""
import os
import time

import pytest

from warpgs.cli import cache as cache_cli
from warpgs.data.cache import cache_dir, cache_entries, least_recently_used, publish_folder


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


def _fake_cache(root):
    """Four entries of known sizes and last-use times (days ago): images 300+100 B (5), priors 200 B (1),
    triangulation 50 B (3), synthetic 1000 B (9); plus a folder being published, which is not an entry."""
    def put(path, nbytes, days):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x" * nbytes)
        return days
    ages = {}
    ages[root / "images" / "ab" / "abcd.png"] = put(root / "images" / "ab" / "abcd.png", 300, 5)
    put(root / "images" / "ab" / "abcd.alpha.png", 100, 5)
    ages[root / "depth_priors" / "k1"] = put(root / "depth_priors" / "k1" / "format.json", 200, 1)
    ages[root / "triangulation" / "k2"] = put(root / "triangulation" / "k2" / "sub" / "points.npz", 50, 3)
    ages[root / "synthetic" / "orbit"] = put(root / "synthetic" / "orbit" / "synthetic.json", 1000, 9)
    put(root / "depth_priors" / ".k3.123.tmp" / "half.json", 7, 0)
    now = time.time()
    for path, days in ages.items():
        os.utime(path, (now - days * 86400, now - days * 86400))
    return ages


def test_cache_entries_and_least_recently_used(tmp_path):
    _fake_cache(tmp_path)
    entries = {e.kind: e for e in cache_entries(tmp_path)}
    assert sorted(entries) == ["depth_priors", "images", "synthetic", "triangulation"]
    assert {k: e.nbytes for k, e in entries.items()} == {"images": 400, "depth_priors": 200, "triangulation": 50,
                                                         "synthetic": 1000}
    # 1650 B in all; to fit 600 B the oldest go first: synthetic (9 d), images (5 d); triangulation (3 d) stays.
    assert [e.kind for e in least_recently_used(list(entries.values()), 600)] == ["synthetic", "images"]
    assert least_recently_used(list(entries.values()), 10_000) == []


def test_warpgs_cache_lists_prunes_and_clears(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path))
    _fake_cache(tmp_path)
    assert cache_cli.main([]) == 0
    out = capsys.readouterr().out
    assert str(tmp_path) in out and "total               4 entries" in out
    assert cache_cli.main(["--max-gb", str(600 / 1e9)]) == 0
    assert "deleted 2 entries" in capsys.readouterr().out
    assert not (tmp_path / "synthetic" / "orbit").exists() and not (tmp_path / "images" / "ab" / "abcd.alpha.png").exists()
    assert (tmp_path / "triangulation" / "k2").is_dir() and (tmp_path / "depth_priors" / "k1").is_dir()
    assert cache_cli.main(["--clear", "triangulation"]) == 0
    assert sorted(e.kind for e in cache_entries(tmp_path)) == ["depth_priors"]
    assert cache_cli.main(["--clear"]) == 0
    assert cache_entries(tmp_path) == [] and (tmp_path / "depth_priors" / ".k3.123.tmp").is_dir()


@pytest.mark.parametrize("argv,message", [(["--clear", "photos"], "unknown kind photos"),
                                          (["--max-gb", "-1"], "--max-gb: expected a size"),
                                          (["--clear", "--max-gb", "1"], "give one of them")])
def test_warpgs_cache_names_a_bad_argument(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.setenv("WARPGS_CACHE", str(tmp_path))
    _fake_cache(tmp_path)
    assert cache_cli.main(argv) == 2
    assert message in capsys.readouterr().err
    assert len(cache_entries(tmp_path)) == 4  # nothing deleted
