"""`choose_lowest_nll`: the one rule by which every `auto` fit option chooses."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from calibrators.core.selection import choose_lowest_nll

nlls = st.one_of(st.none(), st.floats(-1e6, 1e6, allow_nan=False))


@given(st.lists(nlls, min_size=1, max_size=6))
def test_the_lowest_nll_wins_ties_go_first_and_none_never_beats_a_number(values):
    names = [f"m{i}" for i in range(len(values))]
    chosen, candidates = choose_lowest_nll(names, lambda n: {"nll": values[names.index(n)]})
    assert list(candidates) == names   # every candidate, in the order given
    numbers = [v for v in values if v is not None]
    if numbers:
        assert values[names.index(chosen)] == min(numbers)
        assert names.index(chosen) == values.index(min(numbers))   # the first of a tie
    else:
        assert chosen == names[0]


def test_each_candidate_is_scored_once_with_what_its_score_returns():
    calls = []

    def score(name):
        calls.append(name)
        return {"nll": {"a": 2.0, "b": 1.0}[name], "ece": 0.1}

    assert choose_lowest_nll(["a", "b"], score) == ("b", {"a": {"nll": 2.0, "ece": 0.1},
                                                          "b": {"nll": 1.0, "ece": 0.1}})
    assert calls == ["a", "b"]
