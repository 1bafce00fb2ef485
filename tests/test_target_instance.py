"""TargetInstance: a target seen in no mask of its own gets one (alone, and wired in the controller)."""

import dataclasses

import numpy as np
import pytest

from ms_drake.experiments.rollout import build_search
from ms_drake.perception.target_instance import TargetInstance, target_instance
from ms_drake.policies.bin_search import load_bin_search_config
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import set_heap_poses
from ms_drake.types import InstanceMasks, TargetEstimate


def _masks():
    m = np.zeros((2, 20, 30), bool)
    m[0, :, :15] = True  # a big object
    m[1, :, 15:] = True  # another
    return InstanceMasks(m, ("seg_0", "seg_1"), np.array([0.9, 0.8]))


def test_a_target_inside_another_mask_is_cut_out_as_its_own_mask():
    masks = _masks()
    t = np.zeros((20, 30), bool)
    t[5:10, 10:14] = True  # 20 px of target inside mask 0 (mostly another object)
    out, target = target_instance(masks, TargetEstimate(True, t, 0.95, -1))
    assert out.ids == ("seg_0", "seg_1", "seg_2") and target.instance_index == 2
    assert np.array_equal(out.masks[2], t) and not (out.masks[0] & t).any()
    assert out.masks[0].sum() == masks.masks[0].sum() - 20 and np.array_equal(out.masks[1], masks.masks[1])
    assert np.isclose(out.scores[2], 0.95)
    # a mask left with fewer than min_pixels drops out
    whole = np.zeros((20, 30), bool)
    whole[:, 15:] = True
    whole[0, 14] = True
    out2, target2 = target_instance(masks, TargetEstimate(True, whole, 0.9, -1))
    assert out2.ids == ("seg_0", "seg_2") and target2.instance_index == 1


@pytest.mark.parametrize("estimate", [
    TargetEstimate(True, _masks().masks[1].copy(), 0.9, 1),     # it has an instance already
    TargetEstimate(False, np.zeros((20, 30), bool), 0.0, -1),   # not seen
    TargetEstimate(True, np.zeros((20, 30), bool), 0.9, -1),   # seen on no pixel
])
def test_estimates_with_an_instance_or_without_pixels_pass_through(estimate):
    masks = _masks()
    out, target = target_instance(masks, estimate)
    assert out is masks and target is estimate


def test_target_instance_system_alone():
    masks = _masks()
    t = np.zeros((20, 30), bool)
    t[0:5, 0:5] = True
    sys = TargetInstance(width=30, height=20)
    ctx = sys.CreateDefaultContext()
    sys.GetInputPort("masks").FixValue(ctx, masks)
    sys.GetInputPort("target").FixValue(ctx, TargetEstimate(True, t, 0.9, -1))
    out = sys.GetOutputPort("masks").Eval(ctx)
    target = sys.GetOutputPort("target").Eval(ctx)
    assert len(out) == 3 and target.instance_index == 2 and np.array_equal(out.masks[target.instance_index], t)


def test_target_instance_wired_in_the_camera_search(small_heap):
    """In the camera setting the controller cuts a target out of the mask it shares and names it
    after the target (MaskAssociation after it); ground-truth masks have no such stage."""
    heap = dataclasses.replace(small_heap, target_index=0, target=small_heap.objects[0].name)
    s = load_scenario(None, "FloatingGripperBin")
    system = build_search(s, heap, load_bin_search_config("camera", policy="largest", seed=1,
                                                          scenario="FloatingGripperBin"))
    names = [system.controller.GetSubsystemByName(n).get_name() for n in ("target_instance", "mask_association")]
    assert names == ["target_instance", "mask_association"]
    ctx = system.diagram.CreateDefaultContext()
    set_heap_poses(system.station, ctx, heap)
    masks, target = system.output(ctx, "masks"), system.output(ctx, "target")
    assert target.visible and 0 <= target.instance_index < len(masks)
    assert masks.ids[target.instance_index] == system.target_id
    gt = build_search(s, heap, load_bin_search_config("ch7", policy="largest", seed=1))
    assert not gt.controller.HasSubsystemNamed("target_instance")
