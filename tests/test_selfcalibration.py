"""The colour camera found from the data (``slam.data.selfcalibration``): depth's occlusion
edges against colour's edges, on synthetic frames whose colour was warped by a known scale and
shift, and on frames registered already (nothing to change)."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from slam.data.selfcalibration import estimate_color_warp
from slam.data.synthetic import open_synthetic


def _warped(frame, scale, shift):
    """The frame with its colour as a colour camera warped by (scale about the centre, shift)
    from the depth camera would see it (reflected at the border: a real camera sees more)."""
    H, W = frame.depth.shape
    centre = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    offset = (1 - scale) * centre + np.asarray(shift, float)
    A = np.array([[scale, 0, offset[0]], [0, scale, offset[1]]])
    return replace(frame, rgb=cv2.warpAffine(frame.rgb, A, (W, H), flags=cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_REFLECT_101))


@pytest.fixture(scope="module")
def frames():
    seq = open_synthetic("synthetic:walk?frames=60&width=320&height=240")
    return [seq[i] for i in range(0, 60, 6)]


@pytest.mark.parametrize("scale, shift", [(0.90, (4.0, -1.0)), (1.06, (-6.0, 3.0))])
def test_a_known_warp_is_found_and_applied(frames, scale, shift):
    warp = estimate_color_warp([_warped(f, scale, shift) for f in frames])
    assert warp.applied, warp.reason
    assert abs(warp.scale - scale) < 0.015 and abs(warp.shift_x - shift[0]) < 1.5 and abs(warp.shift_y - shift[1]) < 1.5
    assert warp.chamfer_px < 0.8 * warp.identity_chamfer_px and 0 < warp.confidence <= 1
    # Applying it undoes the warp: the colour then matches the depth camera's own view.
    truth, seen = frames[3].rgb, None
    restored, seen = warp.apply(_warped(frames[3], scale, shift).rgb)
    inner = seen.copy()
    inner[:12], inner[-12:], inner[:, :12], inner[:, -12:] = False, False, False, False
    error = np.abs(restored - truth).mean(-1)[inner].mean()
    before = np.abs(_warped(frames[3], scale, shift).rgb - truth).mean(-1)[inner].mean()
    assert error < 0.4 * before, (error, before)


def test_registered_frames_are_left_as_they_are(frames):
    warp = estimate_color_warp(frames)
    assert not warp.applied and "identity" in warp.reason


def test_frames_without_edges_are_never_trusted():
    frame = open_synthetic("synthetic:walk?frames=2&width=64&height=48")[0]
    flat = replace(frame, depth=np.full_like(frame.depth, 2.0))  # a wall: no occlusion edge
    warp = estimate_color_warp([flat, flat])
    assert not warp.applied and warp.frames == 0
