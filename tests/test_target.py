"""TargetDetector: HSV colour and template backends -- alone and wired to a station."""

import copy

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageRgba8U

from ms_drake.objects import TARGET_RGBA
from ms_drake.perception.masks import object_labels
from ms_drake.errors import PerceptionError
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import (Template, TemplateMatcher, TargetDetector, detect_color, red_pixels,
                                        render_templates)
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import InstanceMasks, TargetEstimate

RED = tuple(int(255 * c) for c in TARGET_RGBA[:3])


def rgba_image(rgb: np.ndarray) -> ImageRgba8U:
    img = ImageRgba8U(rgb.shape[1], rgb.shape[0])
    a = np.array(img.mutable_data, copy=False)
    a[:, :, :3] = rgb
    a[:, :, 3] = 255
    return img


def scene():
    """A 100 x 120 picture: a grey, a blue and a red (shaded) object, with their masks."""
    rgb = np.full((100, 120, 3), 30, np.uint8)
    m = np.zeros((3, 100, 120), bool)
    m[0, 10:40, 10:50] = True
    m[1, 50:90, 10:60] = True
    m[2, 20:60, 70:110] = True
    rgb[m[0]] = (150, 150, 150)
    rgb[m[1]] = (60, 90, 200)
    rgb[m[2]] = RED
    rgb[40:60, 70:110] = (120, 10, 10)  # the shaded side of the red object
    return rgb, InstanceMasks(m, ("grey", "blue", "red"), np.ones(3))


def test_color_backend_finds_the_red_mask():
    rgb, masks = scene()
    est = detect_color(rgb, masks)
    assert est.visible and est.instance_index == 2 and est.confidence > 0.9
    assert np.array_equal(est.mask, masks.masks[2])
    # Red pixels that no mask explains still make the target visible, without an instance.
    est = detect_color(rgb, InstanceMasks(masks.masks[:2], masks.ids[:2], np.ones(2)))
    assert est.visible and est.instance_index == -1 and est.mask.sum() == 1600
    # No red at all: not visible.
    rgb[masks.masks[2]] = (150, 150, 150)
    rgb[40:60, 70:110] = (150, 150, 150)
    est = detect_color(rgb, masks)
    assert not est.visible and not est.mask.any() and red_pixels(rgb).sum() == 0


def test_template_backend_scores_masks_against_target_images():
    rgb, masks = scene()
    red_view = Template(rgb[20:60, 70:110].copy(), np.ones((40, 40), bool))
    matcher = TemplateMatcher([red_view], threshold=0.9)
    s = matcher.scores(rgb, masks)
    assert s[2] > 0.99 and s[0] < 0.5 and s[1] < 0.5
    est = matcher.detect(rgb, masks)
    assert est.visible and est.instance_index == 2
    # A partly occluded target (the lower half hidden) still matches; a mask far larger than any
    # template cannot be the target.
    occl = masks.masks.copy()
    occl[2, 40:60] = False
    assert matcher.scores(rgb, InstanceMasks(occl, masks.ids, np.ones(3)))[2] > 0.9
    big = Template(rgb[20:30, 70:80].copy(), np.ones((10, 10), bool))
    assert TemplateMatcher([big]).scores(rgb, masks)[2] == 0.0
    # Templates of another object: no mask reaches t_r = 0.9 ...
    blue_view = Template(rgb[50:90, 10:60].copy(), np.ones((40, 50), bool))
    others = InstanceMasks(masks.masks[[0, 2]], ("grey", "red"), np.ones(2))
    assert (TemplateMatcher([blue_view]).scores(rgb, others) < 0.9).all()
    assert not TemplateMatcher([blue_view], parts=False).detect(rgb, others).visible
    # ... but the blue object's pixels, which no mask holds, are the target seen without an instance.
    est = TemplateMatcher([blue_view]).detect(rgb, others)
    assert est.visible and est.instance_index == -1 and np.array_equal(est.mask, masks.masks[1])
    rgb[masks.masks[1]] = (150, 150, 150)
    assert not TemplateMatcher([blue_view]).detect(rgb, others).visible


def test_detector_alone_fixes_inputs_and_evaluates():
    rgb, masks = scene()
    for det in (TargetDetector("color", 120, 100),
                TargetDetector("template", 120, 100, templates=[Template(rgb[20:60, 70:110].copy(),
                                                                         np.ones((40, 40), bool))])):
        ctx = det.CreateDefaultContext()
        det.GetInputPort("rgb_image").FixValue(ctx, rgba_image(rgb))
        det.GetInputPort("masks").FixValue(ctx, masks)
        est = det.GetOutputPort("target").Eval(ctx)
        assert isinstance(est, TargetEstimate) and est.visible and est.instance_index == 2, det.backend


def test_detector_rejects_bad_configuration():
    with pytest.raises(PerceptionError, match="unknown"):
        TargetDetector("siamese")
    with pytest.raises(PerceptionError, match="at least one template"):
        TargetDetector("template")
    with pytest.raises(PerceptionError, match="t_r"):
        TemplateMatcher([Template(np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), bool))], threshold=1.5)
    det = TargetDetector("color")
    with pytest.raises(PerceptionError, match="not connected"):
        det.GetOutputPort("target").Eval(det.CreateDefaultContext())


def test_detectors_wired_to_a_station(bin_scenario, small_heap):
    k = int(np.argmax(small_heap.visible_ratios))  # draw the most visible object in the target colour
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, target_index=k))
    labels = object_labels(get_plant(station))
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=labels))
    builder.Connect(station.GetOutputPort("overhead.label_image"), seg.GetInputPort("label_image"))
    target_name = small_heap.objects[k].name
    templates = render_templates(bin_scenario, target_name, k=3, seed=1)
    other = next(o.name for o in small_heap.objects if o.name != target_name)
    dets = {"color": TargetDetector("color"),
            "template": TargetDetector("template", templates=templates),
            "other": TargetDetector("template", templates=render_templates(bin_scenario, other, k=3, red=False))}
    for d in dets.values():
        builder.AddSystem(d)
        builder.Connect(station.GetOutputPort("overhead.rgb_image"), d.GetInputPort("rgb_image"))
        builder.Connect(seg.GetOutputPort("masks"), d.GetInputPort("masks"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    masks = seg.GetOutputPort("masks").Eval(seg.GetMyContextFromRoot(ctx))
    model_name = next(n for n in labels.values() if n.startswith(f"obj{k:02d}__"))
    assert len(templates) == 3 and all(t.mask.any() for t in templates)
    for name in ("color", "template"):
        est = dets[name].GetOutputPort("target").Eval(dets[name].GetMyContextFromRoot(ctx))
        assert est.visible, name
        assert masks.ids[est.instance_index] == model_name, name
        assert est.confidence >= (0.9 if name == "template" else 0.5), name
    est = dets["other"].GetOutputPort("target").Eval(dets["other"].GetMyContextFromRoot(ctx))
    # the templates of another object find that object, not the target
    other_index = next(i for i, o in enumerate(small_heap.objects) if o.name == other)
    assert other_index != k and est.visible
    assert masks.ids[est.instance_index] == next(n for n in labels.values() if n.startswith(f"obj{other_index:02d}__"))
