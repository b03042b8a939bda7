"""Speed work changes no answer: the engine against its record (`tests/reference_answers`),
given the fixes one at a time (`Engine.process`) and in batches (`Engine.process_many`)."""

from __future__ import annotations

import pytest

from tests.reference_answers import TOLERANCE_M, cases, compare, load_record


@pytest.mark.parametrize("batch", [1, 50])
def test_the_engine_gives_the_recorded_answers(batch: int) -> None:
    record = load_record()
    built = cases()
    assert {c.name for c in built} == set(record), "a case without a record, or the reverse"
    found = {}
    for case in built:
        other, worst = compare(case, record[case.name], batch)
        if other or worst > TOLERANCE_M:
            found[case.name] = (other, worst)
    assert not found, f"(answers on other lanes, worst difference m) by case: {found}"
