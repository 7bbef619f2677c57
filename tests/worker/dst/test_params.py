import pytest

from worker.dst.errors import InvalidParameters
from worker.dst.params import SliceParams


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("layer_height", 0, "layer_height must be between 0.01 and 2 mm, got 0"),
        ("layer_height", 50, "layer_height must be between 0.01 and 2 mm, got 50"),
        ("chord_error", 0, "chord_error must be between 0.0001 and 1 mm, got 0"),
        ("segment_length", -1, "segment_length must be between 0.01 and 50 mm"),
        ("rotate_y", 361, "rotate_y must be between -360 and 360 degrees, got 361"),
    ],
)
def test_out_of_range_values_name_the_allowed_range(field, value, message):
    with pytest.raises(InvalidParameters, match=message):
        SliceParams.parse(**{field: value})


def test_chord_error_must_be_below_segment_length():
    with pytest.raises(InvalidParameters, match="chord_error .* must be smaller than segment_length"):
        SliceParams.parse(segment_length=0.1, chord_error=0.2)


@pytest.mark.parametrize("mode", ["inclusive", "exclusive"])
def test_prusaslicers_planes_are_refused_in_a_boundary_mode_when_the_parameters_are_read(mode):
    """PrusaSlicer always slices mid-layer: the combination is refused with the request (the API's
    upload, the CLI's options), not when a job plans its planes."""
    with pytest.raises(
        InvalidParameters, match=f"target_slicer 'prusa' only slices in 'middle' mode.*'{mode}'"
    ):
        SliceParams.parse(mode=mode, target_slicer="prusa")
    assert SliceParams.parse(mode=mode, target_slicer="cura").mode == mode
    assert SliceParams.parse(target_slicer="prusa").mode == "middle"


def test_defaults_match_the_documented_ones():
    p = SliceParams.parse()
    assert (p.layer_height, p.h0, p.mode, p.segment_length, p.chord_error) == (0.2, 0.2, "middle", 0.8, 0.025)
