import numpy as np
import pytest

from worker.dst.errors import InvalidParameters, ResourceLimitExceeded
from worker.dst.params import SliceParams
from worker.dst.planes import plan_planes


def test_middle_planes_follow_the_slicer_formula():
    plan = plan_planes(height=1.0, params=SliceParams(layer_height=0.2))
    np.testing.assert_allclose(plan.z, [0.1, 0.3, 0.5, 0.7, 0.9])


def test_first_layer_height_shifts_every_plane():
    plan = plan_planes(height=1.0, params=SliceParams(layer_height=0.2, first_layer_height=0.3))
    np.testing.assert_allclose(plan.z, [0.15, 0.4, 0.6, 0.8])


@pytest.mark.parametrize("mode", ["inclusive", "exclusive"])
def test_boundary_modes_slice_the_layer_boundaries(mode):
    plan = plan_planes(height=1.0, params=SliceParams(layer_height=0.2, first_layer_height=0.3, mode=mode))
    np.testing.assert_allclose(plan.z, [0.1, 0.3, 0.5, 0.7, 0.9])  # max(0, h0 - h), then h0 + k h


def test_cura_planes_are_integer_micrometres_with_integer_division():
    plan = plan_planes(
        height=2.0, params=SliceParams(layer_height=0.2, first_layer_height=0.125, target_slicer="cura")
    )
    um = plan.z * 1000
    np.testing.assert_array_equal(um, np.round(um))
    assert um[0] == 62  # 125 // 2
    assert um[1] == 125 + 100
    # float32 of the plane, read back by Cura as round(z * 1000), is the same integer
    np.testing.assert_array_equal(np.round(plan.z32.astype(np.float64) * 1000), um)


def test_prusa_planes_accumulate_in_double_then_cast_to_float32():
    params = SliceParams(layer_height=0.1, target_slicer="prusa")
    plan = plan_planes(height=30.0, params=params)
    lo, expect = 0.1, [0.05]
    while lo + 0.05 < 30.0:
        expect.append(0.5 * (lo + (lo + 0.1)))
        lo += 0.1
    np.testing.assert_array_equal(plan.z, np.array(expect))
    np.testing.assert_array_equal(plan.z32, np.array(expect, dtype=np.float32))
    # accumulation really differs from the decimal formula somewhere
    decimal = 0.1 + (np.arange(1, len(expect)) - 0.5) * 0.1
    assert np.any(plan.z[1:] != decimal)


def test_planes_stay_strictly_inside_the_part():
    plan = plan_planes(height=0.9, params=SliceParams(layer_height=0.2))
    assert plan.z.max() < 0.9 and plan.z.min() > 0


def test_too_many_planes_is_a_resource_limit():
    with pytest.raises(ResourceLimitExceeded, match="planes"):
        plan_planes(height=100_000.0, params=SliceParams(layer_height=0.2))


def test_prusa_has_no_boundary_modes():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="only slices in 'middle' mode"):
        SliceParams(mode="inclusive", target_slicer="prusa")
    # a copy with updates skips the model's validation: planning refuses it too
    bypass = SliceParams(target_slicer="prusa").model_copy(update={"mode": "inclusive"})
    with pytest.raises(InvalidParameters, match="only slices in 'middle' mode"):
        plan_planes(height=1.0, params=bypass)
