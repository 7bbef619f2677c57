import re

import pytest

from worker.dst.baselines import BASELINE_PRESETS, BASELINES_PATTERN, DEFAULT_BASELINES, parse_baselines
from worker.dst.errors import InvalidParameters

ACCEPTED = [
    "",
    "none",
    "occt_fast",
    " occt_fast , prusaslicer_high ",
    "occt_fast,,none",
    ",".join(BASELINE_PRESETS),
    "prusaslicer,prusaslicer",
]
REFUSED = ["null", "prusaslicer_highx", "occt fast", "OCCT_FAST", "occt_fast;prusaslicer", "none,cura"]


@pytest.mark.parametrize("text", ACCEPTED + REFUSED)
def test_the_schemas_pattern_accepts_exactly_what_the_parser_takes(text):
    """The API documents the baselines field by ``BASELINES_PATTERN``; the parser decides (with a
    message naming the unknown names): both agree."""
    try:
        parse_baselines(text)
        parsed = True
    except InvalidParameters:
        parsed = False
    assert parsed == (text in ACCEPTED)
    assert bool(re.fullmatch(BASELINES_PATTERN, text)) == parsed


def test_parsed_baselines_are_the_named_presets_once_each_in_order():
    assert parse_baselines(None) == DEFAULT_BASELINES
    assert parse_baselines(" occt_fast , prusaslicer_high,occt_fast,none") == (
        "occt_fast",
        "prusaslicer_high",
    )
    assert parse_baselines("none") == parse_baselines("") == ()
    with pytest.raises(InvalidParameters, match="unknown baseline null; choose from occt_fast"):
        parse_baselines("null")
