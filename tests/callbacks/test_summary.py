"""RunSummary's learned-guard warning: plain words for runs that did not learn or were not trained."""

from __future__ import annotations

from tofdenoise.callbacks.summary import format_learned_warning
from tofdenoise.records import learned_verdict


def test_warning_in_plain_words_for_a_run_that_did_not_learn():
    line = format_learned_warning(learned_verdict(89, 7.68, 7.79))
    assert line == (
        "WARNING: the network did not learn: best val MAE 7.68 mm vs raw 7.79 mm "
        "(needs <= 7.40 mm, 5% below raw); treat this run as failed"
    )


def test_warning_for_an_untrained_or_unverified_run_and_none_when_learned():
    assert format_learned_warning(learned_verdict(0, None, None)).startswith(
        "WARNING: the network was not trained: 0 optimiser steps"
    )
    assert "treat this run as unverified" in format_learned_warning(learned_verdict(3, None, 7.0))
    assert format_learned_warning(learned_verdict(900, 2.2, 7.79)) is None
    assert format_learned_warning(None) is None
