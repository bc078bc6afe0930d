"""The human hand's 21 keypoints (MANO's joints with fingertips, the layout of every demo, docs/demo_format.md):
their names, the fingertips and the bones of the skeleton. Shared by the demo format (:mod:`quasisim.data`)
and the hand models (:mod:`quasisim.assets`), which both sit above it."""

from __future__ import annotations

import itertools

N_KEYPOINTS = 21
FINGERTIPS = (4, 8, 12, 16, 20)
KEYPOINT_NAMES = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "little_mcp", "little_pip", "little_dip", "little_tip",
)  # fmt: skip
# Bones of the human hand skeleton as (parent, child) keypoint pairs.
BONES = tuple(
    (a, b)
    for chain in ((0, 1, 2, 3, 4), (0, 5, 6, 7, 8), (0, 9, 10, 11, 12), (0, 13, 14, 15, 16), (0, 17, 18, 19, 20))
    for a, b in itertools.pairwise(chain)
)
