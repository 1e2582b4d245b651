"""Segments: fusion, polarity, detection against projected ground truth, LBD matching, tracking."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.lines import (
    LBD,
    LineConfig,
    LineTracker,
    SegmentDetector,
    fuse_collinear,
    match_keyframe_lines,
    orient_by_polarity,
)
from papl_mapper.frontend.points import PointConfig, PointTracker
from tests.test_frontend_scene import covered_fraction, rendered_walk, segment_match

MIN_RECALL = {"edlines": 0.85, "lsd": 0.75}  # GT segments at least half covered
MIN_PRECISION = {"edlines": 0.5, "lsd": 0.6}  # detections on a GT edge (the rest lie on wall texture)
MIN_MATCH_PRECISION = 0.95  # tracked / LBD-matched pairs on the same GT segment


@pytest.fixture(scope="module")
def walk():
    """24 noisy frames of the test room with their projected GT segments (and GT ids)."""
    frames, _, _, gts = rendered_walk(24)
    return frames, gts


def test_fusion_merges_collinear_fragments_only():
    rng = np.random.default_rng(0)
    a, b = np.array([50.0, 60.0]), np.array([450.0, 260.0])
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([-d[1], d[0]])
    L = np.linalg.norm(b - a)
    pieces = [(0, 120), (126, 250), (255, L)]  # gaps of 6 and 5 px
    frags = [np.concatenate([a + t0 * d, a + t1 * d]) + rng.normal(0, 0.2, 4) for t0, t1 in pieces]
    parallel = np.concatenate([a + 5 * n, b + 5 * n])  # 5 px away: another edge
    far = np.concatenate([a + 300 * d + 20 * n, b + 100 * d + 20 * n])
    cross = np.array([200.0, 50.0, 220.0, 300.0])
    out = fuse_collinear(np.array([*frags, parallel, far, cross]), 2.0, 1.5, 10.0)
    assert len(out) == 4
    merged = out[np.argmin([np.linalg.norm(s[:2] - a) + np.linalg.norm(s[2:] - b) for s in out])]
    ends = sorted([merged[:2], merged[2:]], key=lambda p: p[0])
    np.testing.assert_allclose(ends[0], a, atol=1.0)
    np.testing.assert_allclose(ends[1], b, atol=1.0)
    # fragments farther apart than the gap stay separate
    assert len(fuse_collinear(np.array([frags[0], frags[2]]), 2.0, 1.5, 10.0)) == 2


def test_polarity_puts_the_bright_side_on_the_left():
    img = np.full((200, 200), 50, np.uint8)
    img[:, 100:] = 200  # bright right half; vertical edge at x = 99.5
    for seg in ([99.5, 20, 99.5, 180], [99.5, 180, 99.5, 20]):
        out = orient_by_polarity(np.array([seg], float), img)[0]
        # left normal of p1->p2 is (dy, -dx): pointing +x (bright) requires dy > 0, i.e. downwards
        assert out[3] > out[1]


@pytest.mark.parametrize("detector", ["edlines", "lsd"])
def test_detection_recall_and_precision_against_ground_truth(walk, detector):
    frames, gts = walk
    det = SegmentDetector(LineConfig(detector=detector))
    recall, precision = [], []
    for img, (gt, _) in list(zip(frames, gts, strict=True))[::6]:
        segs = det.detect(img)
        assert segs.shape[1] == 4 and len(segs) <= det.config.max_segments
        lengths = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
        assert lengths.min() >= det.config.min_length_px - 1e-9
        m = segment_match(segs, gt)
        precision.append(np.mean(m >= 0))
        recall.append(np.mean([covered_fraction(segs, gt, m, g) >= 0.5 for g in range(len(gt))]))
    assert np.mean(recall) >= MIN_RECALL[detector]
    assert np.mean(precision) >= MIN_PRECISION[detector]


def test_lbd_keyframe_matching_precision(walk):
    frames, gts = walk
    det = SegmentDetector(LineConfig())
    lbd = LBD()
    cfg = LineConfig()
    a, b = 0, 8  # keyframes 8 frames apart (about 0.25 m and 2.4 degrees)
    sa, sb = det.detect(frames[a]), det.detect(frames[b])
    ra, da = lbd.compute(frames[a], sa)
    rb, db = lbd.compute(frames[b], sb)
    assert da.shape == (len(ra), 32) and da.dtype == np.uint8
    m = match_keyframe_lines(sa[ra], da, sb[rb], db, cfg)
    ga = gts[a][1][segment_match(sa[ra], gts[a][0])] if len(ra) else np.zeros(0)
    gb = gts[b][1][segment_match(sb[rb], gts[b][0])] if len(rb) else np.zeros(0)
    ma, mb = segment_match(sa[ra], gts[a][0]), segment_match(sb[rb], gts[b][0])
    on_gt = (ma[m[:, 0]] >= 0) & (mb[m[:, 1]] >= 0)
    assert on_gt.sum() >= 25
    correct = ga[m[on_gt, 0]] == gb[m[on_gt, 1]]
    assert correct.mean() >= MIN_MATCH_PRECISION


def test_tracking_match_precision_and_persistence(walk):
    frames, gts = walk
    cfg = LineConfig()
    det = SegmentDetector(cfg)
    lt = LineTracker(cfg)
    pt = PointTracker(PointConfig(), FlowConfig(), frames[0].shape[1], frames[0].shape[0])
    gt_of_track: dict[int, int] = {}
    good = bad = 0
    prev = None
    for img, (gt, gid) in zip(frames, gts, strict=True):
        pt.step(img, prev)
        segs = det.detect(img)
        ids = lt.step(
            segs, pt.flow_from if prev is not None else None, pt.flow_to if prev is not None else None
        )
        assert len(np.unique(ids)) == len(ids)
        m = segment_match(segs, gt)
        for t, g in zip(ids.tolist(), m.tolist(), strict=True):
            if g < 0:
                continue
            if t in gt_of_track:
                good += gt_of_track[t] == gid[g]
                bad += gt_of_track[t] != gid[g]
            gt_of_track[t] = gid[g]
        prev = img
    assert good / (good + bad) >= MIN_MATCH_PRECISION
    assert good >= 20 * (len(frames) - 1)  # most GT segments are followed frame to frame


def test_lost_segments_are_reassociated_by_lbd(walk):
    """Detections missing for two frames come back under their old track ids at the next keyframe."""
    frames, gts = walk
    cfg = LineConfig(max_missed_frames=0)  # no coasting: the tracks end and LBD must re-find them
    det = SegmentDetector(cfg)
    lbd = LBD()
    gt_before: dict[int, int] = {}
    lt = LineTracker(cfg)
    pt = PointTracker(PointConfig(), FlowConfig(), frames[0].shape[1], frames[0].shape[0])
    prev = None
    before = None
    for k, img in enumerate(frames[:6]):
        pt.step(img, prev)
        segs = det.detect(img)
        if k in (2, 3):
            segs = segs[len(segs) // 2 :]  # the longest half is not detected
        lt.step(segs, pt.flow_from if prev is not None else None, pt.flow_to if prev is not None else None)
        if k in (1, 4):
            lt.keyframe(img, lbd)
        if k == 1:
            before = set(lt.ids.tolist())
            m = segment_match(lt.segs, gts[k][0])
            gt_before = {
                t: int(gts[k][1][g]) for t, g in zip(lt.ids.tolist(), m.tolist(), strict=True) if g >= 0
            }
        prev = img
    assert len(lt.aliases) >= 10
    assert all(old in before and young not in before for young, old in lt.aliases.items())
    assert len(np.unique(lt.ids)) == len(lt.ids)
    # the re-found segments lie on the same ground-truth edges as before
    m = segment_match(lt.segs, gts[5][0])
    now = {t: int(gts[5][1][g]) for t, g in zip(lt.ids.tolist(), m.tolist(), strict=True) if g >= 0}
    checked = [now[old] == gt_before[old] for old in lt.aliases.values() if old in now and old in gt_before]
    assert len(checked) >= 10 and np.mean(checked) >= MIN_MATCH_PRECISION


def test_missed_detections_coast_on_the_flow(walk):
    """With coasting, segments missing for two frames keep their ids without any re-association."""
    frames, gts = walk
    cfg = LineConfig(max_missed_frames=2, reassociate=False)
    det = SegmentDetector(cfg)
    lt = LineTracker(cfg)
    pt = PointTracker(PointConfig(), FlowConfig(), frames[0].shape[1], frames[0].shape[0])
    prev = None
    hidden = None
    for k, img in enumerate(frames[:6]):
        pt.step(img, prev)
        segs = det.detect(img)
        if k in (2, 3):
            segs = segs[len(segs) // 2 :]
        ids = lt.step(
            segs, pt.flow_from if prev is not None else None, pt.flow_to if prev is not None else None
        )
        if k == 1:
            gt_before = dict(zip(ids.tolist(), segment_match(segs, gts[k][0]).tolist(), strict=True))
            gid_before = gts[k][1]
        if k == 2:
            hidden = set(gt_before) - set(ids.tolist())
        prev = img
    back = hidden & set(ids.tolist())
    assert len(back) >= 10 and not lt.aliases
    m = dict(zip(ids.tolist(), segment_match(segs, gts[5][0]).tolist(), strict=True))
    same = [gts[5][1][m[t]] == gid_before[gt_before[t]] for t in back if m[t] >= 0 and gt_before[t] >= 0]
    assert len(same) >= 10 and np.mean(same) >= MIN_MATCH_PRECISION


@pytest.mark.parametrize("own_motion", [True, False])
def test_segments_keep_their_tracks_where_the_point_flow_predicts_them_wrongly(own_motion):
    """Past a textured stretch onto a blank wall, the few tracked points left lie far from the lines and
    move otherwise (here: the other way); the lines move smoothly, so their own last motion finds them
    again, each on its own track (parallel neighbours 30 px apart never swap). Without it they get new
    ids every frame."""
    lt = LineTracker(LineConfig(own_motion=own_motion))
    base = np.array([[100.0 + 30 * k, 20.0, 104.0 + 30 * k, 400.0] for k in range(5)])  # near-vertical
    pts = np.array([[90.0 + 30 * k, 200.0] for k in range(6)])  # textured: points beside the lines
    wall = np.array([[600.0, 50.0], [620.0, 60.0], [610.0, 440.0]])  # blank wall: few points, far away
    ids = []
    for f in range(8):
        segs = base + [9.0 * f, 0.4 * f, 9.0 * f, 0.4 * f]  # 9 px per frame to the right
        if f == 0:
            flow = (None, None)
        elif f < 3:
            flow = (pts + [9.0 * (f - 1), 0.4 * (f - 1)], pts + [9.0 * f, 0.4 * f])
        else:
            flow = (wall, wall - [6.0, 0.0])
        ids.append(lt.step(segs, *flow))
    assert all(np.array_equal(i, ids[0]) for i in ids[:3])  # the point flow carries them
    if own_motion:
        assert all(np.array_equal(i, ids[0]) for i in ids)
    else:
        assert not set(ids[-1].tolist()) & set(ids[0].tolist())
