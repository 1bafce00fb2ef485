"""Category-agnostic instance segmentation of a bin (Ch. 5; App. B): the `Segmenter` LeafSystem.

Backends (``Segmenter(backend=...)``):

- ``ground_truth`` (simulation only): the label image of the RgbdSensor, one mask per object
  (``ms_drake.perception.masks.label_image_to_masks``).
- ``euclidean``: PCL-style Euclidean clustering of the point cloud with the bin removed. The
  depth image is deprojected to the world, cropped to the bin's inner box above the floor
  (`Workspace.foreground`), subsampled on a `stride` x `stride` pixel grid (the role of PCL's
  voxel filter), and points closer than `tolerance` are joined (scipy cKDTree pairs + sparse
  connected components). Clusters with `min_pixels`..`max_pixels` pixels (full resolution)
  are kept; every foreground pixel takes the cluster of its nearest sampled point within
  `tolerance`, which projects the clusters back to image masks.
- ``learned``: the network of ms_drake.perception.segmentation_net trained on synthetic depth
  images (``ms-drake train segmentation``; see that module for the design), depth only.
- ``region_growing``: PCL-style smoothness region growing on the organized cloud. Per pixel a
  normal and a curvature (surface variation lambda_0 / (lambda_0 + lambda_1 + lambda_2)) come
  from a PCA of the `window` x `window` neighbourhood; 8-neighbours are "smooth" when their
  normals differ by less than `smoothness_deg` and their points by less than `tolerance`.
  PCL grows regions from seeds in order of curvature and lets only points with curvature below
  `curvature_threshold` propagate; the same partition is computed here without a queue: the
  connected components of the smooth graph restricted to low-curvature points are the regions,
  and each high-curvature point joins a region it has a smooth edge to (else it is dropped).

Masks are sorted by decreasing area, ids ``seg_<k>``; the PCL baselines have no confidence, so
every score is 1 (COCO AP then ranks them by order, as the reference's single operating point).
Parameter defaults were tuned on heaps outside the benchmark seeds (sims/bench_segmentation.py).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ms_drake.errors import PerceptionError
from ms_drake.geometry import PinholeCamera, Workspace, depth_array, preprocess_depth, world_points
from ms_drake.perception.masks import label_image_to_masks
from ms_drake.perception.segmentation_net import LearnedSegmentation
from ms_drake.types import InstanceMasks

BACKENDS = ("ground_truth", "euclidean", "region_growing", "learned")



@dataclass(frozen=True)
class EuclideanParams:
    tolerance: float = 0.005  # m: cluster tolerance (PCL's ClusterTolerance)
    stride: int = 2  # pixel subsampling before clustering
    min_pixels: int = 150
    max_pixels: int = 200000
    min_height: float = 0.004  # m above the floor: points below are the bin


def euclidean_clustering(P_W: np.ndarray, workspace: Workspace, params: EuclideanParams = EuclideanParams()
                         ) -> InstanceMasks:
    """Euclidean clustering of the organized world cloud `P_W` (H, W, 3); see the module doc."""
    h, w = P_W.shape[:2]
    fg = workspace.foreground(P_W, params.min_height)
    s = max(1, int(params.stride))
    sub = np.zeros_like(fg)
    sub[::s, ::s] = fg[::s, ::s]
    idx = np.flatnonzero(sub)
    labels = np.full(h * w, -1, np.int64)
    if len(idx) == 0:
        return InstanceMasks.empty(h, w)
    pts = P_W.reshape(-1, 3)[idx]
    tree = cKDTree(pts)
    pairs = tree.query_pairs(params.tolerance, output_type="ndarray")
    g = sparse.coo_matrix((np.ones(len(pairs), bool), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    _, comp = connected_components(g, directed=False)
    full = np.flatnonzero(fg)
    dist, near = tree.query(P_W.reshape(-1, 3)[full], k=1, distance_upper_bound=params.tolerance)
    ok = np.isfinite(dist)
    labels[full[ok]] = comp[near[ok]]
    return label_image_to_masks(labels.reshape(h, w), None, params.min_pixels, params.max_pixels)


@dataclass(frozen=True)
class RegionGrowingParams:
    smoothness_deg: float = 6.0  # max angle between neighbouring normals
    curvature_threshold: float = 0.03  # points below may propagate a region (PCL's curvature threshold)
    tolerance: float = 0.004  # m: max distance between neighbouring points (depth discontinuities)
    window: int = 5  # PCA neighbourhood for normals and curvature (pixels)
    min_pixels: int = 150
    max_pixels: int = 200000
    min_height: float = 0.004


def normals_and_curvature(P_W: np.ndarray, valid: np.ndarray, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel unit normals (H, W, 3, pointing up, +z) and curvature (surface variation) from a
    PCA of the valid points in a `window` x `window` neighbourhood (box filters of the moments)."""
    wgt = valid.astype(np.float64)
    P = np.where(valid[..., None], P_W, 0.0)
    k = (int(window), int(window))
    n = cv2.boxFilter(wgt, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    nz = np.maximum(n, 1.0)
    mean = np.stack([cv2.boxFilter(P[..., i], -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
                     for i in range(3)], axis=-1) / nz[..., None]
    C = np.empty(P.shape[:2] + (3, 3))
    for i in range(3):
        for j in range(i, 3):
            m = cv2.boxFilter(P[..., i] * P[..., j], -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT) / nz
            C[..., i, j] = C[..., j, i] = m - mean[..., i] * mean[..., j]
    evals, evecs = np.linalg.eigh(C[valid])
    normals = np.zeros(P.shape)
    curv = np.ones(P.shape[:2])
    nrm = evecs[:, :, 0]
    nrm *= np.where(nrm[:, 2:3] < 0, -1.0, 1.0)
    normals[valid] = nrm
    tot = evals.sum(axis=1)
    curv[valid] = np.where(tot > 1e-12, np.clip(evals[:, 0], 0, None) / np.maximum(tot, 1e-12), 0.0)
    curv[valid & (n < 3)] = 1.0
    return normals, curv


_OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1))


def region_growing(P_W: np.ndarray, workspace: Workspace, params: RegionGrowingParams = RegionGrowingParams()
                   ) -> InstanceMasks:
    """Smoothness region growing on the organized world cloud `P_W`; see the module doc."""
    h, w = P_W.shape[:2]
    fg = workspace.foreground(P_W, params.min_height)
    if not fg.any():
        return InstanceMasks.empty(h, w)
    normals, curv = normals_and_curvature(P_W, fg, params.window)
    cos_t = np.cos(np.radians(params.smoothness_deg))
    low = fg & (curv < params.curvature_threshold)
    flat = np.arange(h * w).reshape(h, w)
    rows, cols, smooth_pairs = [], [], []
    for dy, dx in _OFFSETS:
        ys = slice(0, h - dy)
        xa = slice(max(0, -dx), w - max(0, dx))
        xb = slice(max(0, dx), w + min(0, dx))
        a = (ys, xa)
        b = (slice(dy, h), xb)
        both = fg[a] & fg[b]
        smooth = both & (np.einsum("ijk,ijk->ij", normals[a], normals[b]) > cos_t) & (
            np.linalg.norm(np.nan_to_num(P_W[a] - P_W[b]), axis=-1) < params.tolerance)
        smooth_pairs.append((flat[a][smooth], flat[b][smooth]))
        grow = smooth & low[a] & low[b]
        rows.append(flat[a][grow])
        cols.append(flat[b][grow])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = sparse.coo_matrix((np.ones(len(r), bool), (r, c)), shape=(h * w, h * w))
    _, comp = connected_components(g, directed=False)
    labels = np.where(low.ravel(), comp, -1)
    # High-curvature points join a region they have a smooth edge to (first found, in offset order).
    lab_flat = labels.copy()
    for pa, pb in smooth_pairs:
        for src, dst in ((pa, pb), (pb, pa)):
            take = (lab_flat[dst] < 0) & (labels[src] >= 0)
            dst_t, src_t = dst[take], src[take]
            _, first = np.unique(dst_t, return_index=True)
            lab_flat[dst_t[first]] = labels[src_t[first]]
    return label_image_to_masks(lab_flat.reshape(h, w), None, params.min_pixels, params.max_pixels)


class Segmenter(LeafSystem):
    """Instance segmentation of the bin from a depth image (see the module doc for backends).

    Inputs ``depth_image`` (ImageDepth32F, metres) and ``label_image`` (ImageLabel16I; only the
    ground_truth backend reads it); output ``masks`` (InstanceMasks).

    backend: ground_truth | euclidean | region_growing | learned.
    camera: PinholeCamera of the depth camera (intrinsics and world pose), for the point-cloud
    backends (the learned backend needs none: it works on the 640 x 480 overhead image).
    workspace: the bin's inner box (Workspace.from_scenario), for the point-cloud backends.
    label_to_id: render label -> object id (masks.object_labels(plant)), for ground_truth.
    params: EuclideanParams / RegionGrowingParams (defaults: tuned values).
    weights: the learned backend's weights file (default: the shipped models/weights/segmentation.pt);
    device: where its network runs (cpu | cuda | auto).
    fill_holes: the depth backends read the depth through geometry.preprocess_depth (the sensor's
    holes filled; a clean render is unchanged); False reads the raw depth (for ablations).
    """

    def __init__(self, backend: str, camera: PinholeCamera | None = None, workspace: Workspace | None = None,
                 label_to_id: dict[int, str] | None = None, params=None, min_pixels: int = 20, weights=None,
                 fill_holes: bool = True, device="cpu"):
        super().__init__()
        if backend not in BACKENDS:
            raise PerceptionError(f"Segmenter backend {backend!r} unknown; choose one of {', '.join(BACKENDS)}")
        if backend == "ground_truth" and label_to_id is None:
            raise PerceptionError("Segmenter(backend='ground_truth') needs label_to_id "
                                  "(ms_drake.perception.masks.object_labels(plant))")
        if backend in ("euclidean", "region_growing") and (camera is None or workspace is None):
            raise PerceptionError(f"Segmenter(backend={backend!r}) needs camera= (PinholeCamera.from_config) "
                                  "and workspace= (Workspace.from_scenario)")
        w, h = (camera.width, camera.height) if camera is not None else (640, 480)
        # Ports first.
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.label_port = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(ImageLabel16I(w, h)))
        self.masks_port = self.DeclareAbstractOutputPort(
            "masks", lambda: AbstractValue.Make(InstanceMasks.empty(h, w)), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.backend = backend
        self.camera, self.workspace = camera, workspace
        self.label_to_id = dict(label_to_id or {})
        self.min_pixels = int(min_pixels)
        if params is None:
            params = {"euclidean": EuclideanParams(), "region_growing": RegionGrowingParams()}.get(backend)
        self.params = params
        self.learned = LearnedSegmentation(weights, device=device) if backend == "learned" else None
        self.fill_holes = bool(fill_holes)

    def segment(self, depth=None, labels=None) -> InstanceMasks:
        """The computation behind the output port (depth: (H, W) metres; labels: (H, W) ints)."""
        if self.backend == "ground_truth":
            if labels is None:
                raise PerceptionError("Segmenter(ground_truth): connect or fix the label_image input")
            return label_image_to_masks(np.asarray(labels), self.label_to_id, self.min_pixels)
        if depth is None:
            raise PerceptionError(f"Segmenter({self.backend}): connect or fix the depth_image input")
        if self.fill_holes:
            depth = preprocess_depth(depth)
        if self.backend == "learned":
            return self.learned.segment(depth_array(depth))
        P_W = world_points(self.camera, depth_array(depth))
        if self.backend == "euclidean":
            return euclidean_clustering(P_W, self.workspace, self.params)
        return region_growing(P_W, self.workspace, self.params)

    def _calc(self, context, output):
        if self.backend == "ground_truth":
            if not self.label_port.HasValue(context):
                raise PerceptionError("Segmenter(ground_truth): the label_image input is not connected")
            output.set_value(self.segment(labels=np.array(self.label_port.Eval(context).data)[:, :, 0]))
        else:
            if not self.depth_port.HasValue(context):
                raise PerceptionError(f"Segmenter({self.backend}): the depth_image input is not connected")
            output.set_value(self.segment(depth=self.depth_port.Eval(context)))


def encode_masks(masks: InstanceMasks) -> dict:
    """{"shape": (H, W), "rles": COCO RLEs, "scores"} of InstanceMasks (compact, picklable)."""
    h, w = masks.masks.shape[1:]
    rles = [mask_utils.encode(np.asfortranarray(masks.masks[k].astype(np.uint8))) for k in range(len(masks))]
    return {"shape": (int(h), int(w)), "rles": rles, "scores": [float(v) for v in masks.scores]}


def coco_metrics(ground_truth: list[dict], predictions: list[dict]) -> dict:
    """COCO mask AP (IoU 0.50:0.95), AP50 and AR@100 (pycocotools) of `predictions` against
    `ground_truth`, both lists of `encode_masks` dicts, one pair per image.
    Returns {"AP", "AP50", "AR100", "images", "gt", "dt"}."""
    if len(ground_truth) != len(predictions):
        raise PerceptionError("coco_metrics: give one prediction per ground-truth image")
    images, anns, dets = [], [], []
    for i, (gt, dt) in enumerate(zip(ground_truth, predictions)):
        h, w = gt["shape"]
        images.append({"id": i, "height": int(h), "width": int(w)})
        for rle in gt["rles"]:
            anns.append({"id": len(anns) + 1, "image_id": i, "category_id": 1, "segmentation": rle,
                         "area": float(mask_utils.area(rle)), "bbox": list(mask_utils.toBbox(rle)), "iscrowd": 0})
        for rle, score in zip(dt["rles"], dt["scores"]):
            dets.append({"image_id": i, "category_id": 1, "segmentation": rle, "score": float(score)})
    coco = COCO()
    coco.dataset = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "object"}]}
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
        if not dets:
            return {"AP": 0.0, "AP50": 0.0, "AR100": 0.0, "images": len(images), "gt": len(anns), "dt": 0}
        coco_dt = coco.loadRes(dets)
        ev = COCOeval(coco, coco_dt, "segm")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return {"AP": float(ev.stats[0]), "AP50": float(ev.stats[1]), "AR100": float(ev.stats[8]),
            "images": len(images), "gt": len(anns), "dt": len(dets)}


def coco_mask_metrics(ground_truth: list[InstanceMasks], predictions: list[InstanceMasks]) -> dict:
    """COCO mask AP (IoU 0.50:0.95) and AR@100 of `predictions` against `ground_truth`, one pair of
    InstanceMasks per image (pycocotools). Returns {"AP", "AP50", "AR100", "images", "gt", "dt"}."""
    if len(ground_truth) != len(predictions):
        raise PerceptionError("coco_mask_metrics: give one prediction per ground-truth image")
    return coco_metrics([encode_masks(g) for g in ground_truth], [encode_masks(p) for p in predictions])
