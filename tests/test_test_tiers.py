"""tests/conftest.py: the slow tier's list of cases is checked against the collection."""

from conftest import SLOW_CASES, dead_slow_cases


def test_an_entry_matching_no_collected_test_is_dead():
    ids = [
        "tests/test_golden.py::test_forward_matches_saved[f/afonftsmc/s1/sign/soe]",
        "tests/test_golden.py::test_other",
        "tests/test_plant.py::test_x",
    ]
    golden = [e for e in SLOW_CASES if e.startswith("test_golden.py::")]
    # test_golden.py was collected whole: every golden entry but the matching one is dead.
    dead = dead_slow_cases(ids)
    assert "test_golden.py::test_forward_matches_saved[f/afonftsmc/s1" not in dead
    assert set(dead) == set(golden) - {"test_golden.py::test_forward_matches_saved[f/afonftsmc/s1"}
    # Files not collected, or selected by test id, are not judged.
    assert dead_slow_cases(ids, partial_files={"test_golden.py"}) == []
    assert dead_slow_cases(["tests/test_plant.py::test_x"]) == []
