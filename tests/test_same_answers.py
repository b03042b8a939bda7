"""Speed work changes no answer: the engine against its record (`tests/reference_answers`)."""

from __future__ import annotations

from tests.reference_answers import TOLERANCE_M, cases, compare, load_record


def test_the_engine_gives_the_recorded_answers() -> None:
    record = load_record()
    built = cases()
    assert {c.name for c in built} == set(record), "a case without a record, or the reverse"
    found = {}
    for case in built:
        other, worst = compare(case, record[case.name])
        if other or worst > TOLERANCE_M:
            found[case.name] = (other, worst)
    assert not found, f"(answers on other lanes, worst difference m) by case: {found}"
