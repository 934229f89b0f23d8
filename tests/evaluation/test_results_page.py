"""docs/results.md is generated from the kept summaries (common/evaluation/results_page.py)."""
import json

import pytest

from common.evaluation.results_page import (
    PAGE,
    SETS,
    ResultsError,
    load_results,
    load_sets,
    main,
    page,
    summary,
)


def test_the_committed_page_is_what_the_summaries_give():
    sets = load_sets()
    results = load_results(sets, SETS.parent)
    assert sets[0]["name"] in results, "the standard set's summary is kept"
    assert PAGE.read_text() == page(sets, results), "docs/results.md is stale: run needletrack results page"


def test_a_summary_keeps_no_machine_path_nor_per_run_lists():
    kept = summary({"dataset": "/home/me/data/test", "node_counters": {"a": 1}, "overlays": ["x.png"],
                    "pose": {}, "frames": 3}, "standard")
    assert kept == {"pose": {}, "frames": 3, "set": "standard"}
    for f in SETS.parent.glob("*.json"):
        text = f.read_text()
        assert "/work/" not in text and "/home/" not in text and "node_counters" not in text, f


@pytest.mark.parametrize("doc, message", [
    ("sets: []", "non-empty list 'sets'"),
    ("sets: [{name: a, title: A, family: in-look, make: 'dataset generate', eval: ''}]", "must write to {dir}"),
    ("sets: [{name: a, title: A, family: other, make: '{dir}', eval: ''}]", "sets[0].family"),
    ("sets: [{name: a, title: A, family: in-look, make: '{dir}'}]", "sets[0].eval: expected a string"),
])
def test_a_bad_sets_file_is_refused_naming_the_field(tmp_path, doc, message):
    f = tmp_path / "sets.yaml"
    f.write_text(doc)
    with pytest.raises(ResultsError, match=message.replace("[", r"\[").replace("]", r"\]").replace("{", r"\{")
                       .replace("}", r"\}")):
        load_sets(f)


@pytest.mark.graph
def test_results_run_makes_evaluates_keeps_and_writes_the_page(tmp_path):
    sets = tmp_path / "results" / "sets.yaml"
    sets.parent.mkdir()
    sets.write_text("sets:\n"
                    "  - {name: tiny, title: tiny set, family: held-out, eval: --detector oracle,\n"
                    "     make: 'dataset generate-alt --out {dir} --sequences 1 --steps 2 --seed 4"
                    " --width 320 --height 180 --quiet'}\n")
    out_page = tmp_path / "results.md"
    assert main(["run", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "evals"),
                 "--sets", str(sets), "--page", str(out_page)]) == 0
    kept = json.loads((sets.parent / "tiny.json").read_text())
    assert kept["set"] == "tiny" and kept["frames"] == 2 and "dataset" not in kept
    text = out_page.read_text()
    assert "| tiny set | held-out | 100.0% |" in text and "0.00 / 0.00" in text
    assert main(["run", "--data", str(tmp_path / "data"), "--only", "nope", "--sets", str(sets)]) == 2
