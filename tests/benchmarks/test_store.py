"""One stored result file per dataset (benchmarks/store.py): rows are kept per configuration, written
atomically, and an old append-only runs file is read beside them."""

import json

from benchmarks.store import RunStore, config_name, source_digest, write_atomic

CONFIG = {"quick": True, "fit": 8, "check": 4, "frames": 300, "tool": 12}


def test_a_row_is_one_file_under_its_configuration_and_read_back_only_with_it(tmp_path):
    store = RunStore.for_runs(tmp_path / "x.runs")
    path = store.save({"key": "elastica:light:none:0", "config": CONFIG, "selected": []})
    assert path == tmp_path / "x.runs" / config_name(CONFIG) / "elastica.light.none.0.json"
    assert config_name(CONFIG) == "check=4-fit=8-frames=300-quick=true-tool=12"
    assert store.has("elastica:light:none:0", CONFIG)
    assert store.load(CONFIG) == {"elastica:light:none:0": json.loads(path.read_text())}
    other = {**CONFIG, "tool": 11}
    assert store.load(other) == {} and not store.has("elastica:light:none:0", other)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


def test_rows_of_an_old_runs_file_count_and_a_new_file_takes_precedence(tmp_path):
    old = [
        {"key": "none:0", "config": CONFIG, "selected": ["old"]},
        {"key": "none:1", "config": CONFIG, "selected": ["old"]},
        {"key": "none:0", "config": {**CONFIG, "tool": 2}, "selected": ["older"]},
    ]
    (tmp_path / "x.runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in old))
    store = RunStore.for_runs(tmp_path / "x.runs.jsonl")  # the old name works too
    assert store.directory == tmp_path / "x.runs"
    assert {k: r["selected"] for k, r in store.load(CONFIG).items()} == {"none:0": ["old"], "none:1": ["old"]}
    store.save({"key": "none:1", "config": CONFIG, "selected": ["new"]})
    assert store.load(CONFIG)["none:1"]["selected"] == ["new"]
    assert (tmp_path / "x.runs.jsonl").read_text().count("\n") == 3  # never written


def test_a_long_configuration_gets_a_short_name_of_its_own():
    a = config_name({"train_args": ["--iterations", "400"] * 40})
    b = config_name({"train_args": ["--iterations", "401"] * 40})
    assert len(a) < 160 and a != b
    assert (
        config_name({"train_args": ["--iterations", "2", "--batch", "4"]})
        == "train_args=--iterations,2,--batch,4"
    )


def test_an_atomic_write_replaces_the_whole_file(tmp_path):
    path = tmp_path / "sub" / "r.json"
    write_atomic(path, "a" * 1000)
    write_atomic(path, "b")
    assert path.read_text() == "b" and [p.name for p in path.parent.iterdir()] == ["r.json"]


def test_the_source_digest_changes_with_the_code_and_only_with_it(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "notes.txt").write_text("not code")
    before = source_digest("pkg", root=tmp_path)
    (tmp_path / "pkg" / "notes.txt").write_text("other")
    assert source_digest("pkg", root=tmp_path) == before
    (tmp_path / "pkg" / "a.py").write_text("x = 2\n")
    assert source_digest("pkg", root=tmp_path) != before
