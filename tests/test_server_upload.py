"""Untrusted input checks of server.upload: zips and streamed frames (no server, no runtime)."""

from __future__ import annotations

import io
import stat
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from server.upload import (
    UploadError,
    ZipLimits,
    check_zip,
    dataset_root,
    decode_color,
    decode_depth,
    decode_stream_frame,
    extract_zip,
    member_path,
    parse_intrinsics,
)

LIMITS = ZipLimits(max_entries=100, max_unzipped_bytes=1_000_000)


def png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def make_zip(path: Path, entries: dict[str, bytes], links: dict[str, str] | None = None) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
        for name, target in (links or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            archive.writestr(info, target)
    return path


@pytest.mark.parametrize("name, reason", [
    ("/etc/passwd", "absolute"),
    ("C:/windows/x", "absolute"),
    ("data/../../escape.txt", "'..'"),
    ("..", "'..'"),
    ("a\\b.txt", "backslash"),
])
def test_member_path_refuses_escaping_names(name, reason):
    with pytest.raises(UploadError, match=reason) as info:
        member_path(name)
    assert info.value.status == 422


def test_member_path_normalises_harmless_names():
    assert str(member_path("./seq/rgb/0.png")) == "seq/rgb/0.png"
    assert member_path("seq/") is None


def test_zip_with_escaping_entry_is_refused_before_anything_is_written(tmp_path):
    archive = make_zip(tmp_path / "bad.zip", {"ok.txt": b"1", "../outside.txt": b"2"})
    with pytest.raises(UploadError, match="escape"):
        extract_zip(archive, tmp_path / "out", LIMITS)
    assert not (tmp_path / "outside.txt").exists()
    assert not (tmp_path / "out" / "ok.txt").exists()


def test_zip_with_symlink_is_refused(tmp_path):
    archive = make_zip(tmp_path / "link.zip", {"a.txt": b"1"}, links={"passwd": "/etc/passwd"})
    with pytest.raises(UploadError, match="links"):
        check_zip(archive, LIMITS)


def test_zip_limits_on_entries_and_uncompressed_size(tmp_path):
    many = make_zip(tmp_path / "many.zip", {f"f{i}.txt": b"x" for i in range(101)})
    with pytest.raises(UploadError, match="101 entries") as info:
        check_zip(many, LIMITS)
    assert info.value.status == 413
    # Highly compressible: small on the wire, over the limit once unpacked.
    bomb = make_zip(tmp_path / "bomb.zip", {"zeros.bin": bytes(2_000_000)})
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("zeros.bin", bytes(2_000_000))
    assert bomb.stat().st_size < 100_000
    with pytest.raises(UploadError, match="uncompressed-size limit") as info:
        check_zip(bomb, LIMITS)
    assert info.value.status == 413


def test_not_a_zip_is_a_400(tmp_path):
    path = tmp_path / "x.zip"
    path.write_bytes(b"this is not a zip")
    with pytest.raises(UploadError, match="not a valid zip") as info:
        check_zip(path, LIMITS)
    assert info.value.status == 400


def test_extraction_and_single_top_folder(tmp_path):
    archive = make_zip(tmp_path / "ok.zip", {"seq/rgb.txt": b"# x", "seq/rgb/1.png": b"p", "__MACOSX/seq/._x": b""})
    out = extract_zip(archive, tmp_path / "out", LIMITS)
    assert (out / "seq" / "rgb" / "1.png").read_bytes() == b"p"
    assert dataset_root(out) == out / "seq"


@pytest.mark.parametrize("top", ["", "Replica/"])
def test_replica_scene_beside_its_cam_params_is_the_root(tmp_path, top):
    """NICE-SLAM's layout: cam_params.json one level above the scene folder, zipped from that
    level (or from the folder holding both)."""
    archive = make_zip(tmp_path / "replica.zip", {f"{top}cam_params.json": b"{}", f"{top}room0/traj.txt": b"",
                                                 f"{top}room0/results/frame000000.jpg": b"x"})
    out = tmp_path / "out"
    extract_zip(archive, out, LIMITS)
    assert dataset_root(out) == out / top / "room0"


def test_several_scenes_beside_cam_params_stay_at_the_top(tmp_path):
    archive = make_zip(tmp_path / "two.zip", {"cam_params.json": b"{}", "room0/traj.txt": b"",
                                             "room1/traj.txt": b""})
    extract_zip(archive, tmp_path / "out", LIMITS)
    assert dataset_root(tmp_path / "out") == tmp_path / "out"


def test_depth_must_be_16_bit_png():
    with pytest.raises(UploadError, match="16-bit PNG, got 8-bit"):
        decode_depth(png(np.zeros((4, 5), np.uint8)))
    with pytest.raises(UploadError, match="not a PNG"):
        decode_depth(cv2.imencode(".jpg", np.zeros((4, 5), np.uint8))[1].tobytes())
    with pytest.raises(UploadError, match="single-channel"):
        decode_depth(png(np.zeros((4, 5, 3), np.uint16)))
    depth = np.arange(20, dtype=np.uint16).reshape(4, 5) * 1000
    assert np.array_equal(decode_depth(png(depth)), depth)


def test_corrupt_and_truncated_images_are_refused():
    good = png(np.full((8, 8, 3), 128, np.uint8))
    with pytest.raises(UploadError, match="cannot decode"):
        decode_color(good[: len(good) // 2])
    with pytest.raises(UploadError, match="not a PNG or JPEG"):
        decode_color(b"garbage bytes that are no image")
    with pytest.raises(UploadError, match="empty"):
        decode_color(b"")


def test_color_is_returned_as_rgb():
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 0] = 255  # blue in OpenCV order
    assert decode_color(png(bgr))[0, 0].tolist() == [0, 0, 255]


def test_frame_sizes_must_match():
    color = png(np.zeros((6, 8, 3), np.uint8))
    depth = png(np.zeros((6, 7), np.uint16))
    with pytest.raises(UploadError, match="color is 8x6 but depth is 7x6"):
        decode_stream_frame(color, depth, 0.0, 1000.0, np.eye(3))


def test_oversized_frame_header_is_refused_before_decoding():
    header = io.BytesIO(png(np.zeros((1, 1), np.uint16)))
    data = bytearray(header.getvalue())
    data[16:24] = (100_000).to_bytes(4, "big") + (10).to_bytes(4, "big")  # claim 100000 x 10 pixels
    with pytest.raises(UploadError, match="100000x10 pixels is over the limit") as info:
        decode_depth(bytes(data))
    assert info.value.status == 413


def test_oversized_jpeg_header_is_refused_before_decoding():
    """A JPEG's size sits in its start-of-frame segment, after any APPn block: found there too."""
    data = bytearray(cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes())
    sof = next(i for i in range(2, len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xC0)
    data[sof + 5:sof + 9] = (60000).to_bytes(2, "big") + (60000).to_bytes(2, "big")
    with pytest.raises(UploadError, match="60000x60000 pixels is over the limit") as info:
        decode_color(bytes(data))
    assert info.value.status == 413


@pytest.mark.parametrize("text", ["1,2,3", "a,b,c,d", "0,1,2,3", "1,2,nan,3"])
def test_bad_intrinsics(text):
    with pytest.raises(UploadError, match="intrinsics"):
        parse_intrinsics(text)


def test_intrinsics_parse():
    assert parse_intrinsics(" 525, 525,319.5,239.5") == (525.0, 525.0, 319.5, 239.5)
