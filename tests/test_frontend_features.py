"""The match graph of the wide-baseline features: weak links, which pairs are matched, track chaining."""

from __future__ import annotations

import numpy as np

from papl_mapper.frontend.features import FeatureConfig, candidate_pairs, chain_tracks, weak_links


def test_weak_links_count_the_tracks_consecutive_keyframes_share():
    # frames 0, 1, 2 (rows in frame order): 0 and 1 share tracks 1-3, 1 and 2 share only track 3
    frame = np.array([0, 0, 0, 1, 1, 1, 2, 2])
    track = np.array([1, 2, 3, 1, 2, 3, 3, 9])
    assert weak_links(frame, track, np.array([0, 1, 2]), 2).tolist() == [False, True]
    assert weak_links(frame, track, np.array([0, 2]), 2).tolist() == [True]


def test_only_pairs_across_a_weak_link_within_the_window_are_matched():
    cfg = FeatureConfig(window=2, exhaustive_below=0)
    weak = np.array([False, False, True, False, False])  # keyframes 0..5, the link 2-3 is weak
    pairs = candidate_pairs(np.arange(6), weak, cfg)
    assert sorted(pairs) == [(1, 3), (2, 3), (2, 4)]
    assert candidate_pairs(np.arange(6), np.zeros(5, bool), cfg) == []
    # a photo set (every link weak, few keyframes): every pair
    assert len(candidate_pairs(np.arange(6), np.ones(5, bool), FeatureConfig())) == 15


def test_chaining_never_puts_two_observations_of_a_track_in_one_frame():
    node_frame = np.array([0, 0, 1, 1, 2])
    # good chain 0-2-4 (cost 1), 1-3 (cost 1); a worse edge 3-4 would join 1-3 with 0-2-4, which
    # holds frame 1 already (node 2): refused; so would 0-1 (same frame)
    edges = np.array([[0, 2], [2, 4], [1, 3], [3, 4], [0, 1]])
    cost = np.array([1.0, 1.0, 1.0, 5.0, 9.0])
    label = chain_tracks(node_frame, edges, cost)
    assert label[0] == label[2] == label[4] and label[1] == label[3] and label[0] != label[1]
    for t in set(label.tolist()):
        frames = node_frame[label == t]
        assert len(frames) == len(set(frames.tolist()))
    assert (chain_tracks(np.array([0, 1, 2]), np.zeros((0, 2), np.int64), np.zeros(0)) == -1).all()
