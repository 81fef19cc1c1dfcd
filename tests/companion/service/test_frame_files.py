"""Frames that are not whole images (issue 61, item 8): a JPEG cut short decodes partly in OpenCV
(the rest flat grey) and must be counted and dropped, from a folder and from an MJPEG stream; a
frames folder where no image decodes is a start-up error (exit 2) naming the folder. Real files
written in tmp_path, real OpenCV, a real MJPEG server on loopback, the real command line."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.frames import decode_image, read_image, truncated_jpeg
from companion.service.camera import CameraError, CameraSource, check_source
from tests import early
from tests.companion.service.test_camera_sources import _collect, _ScriptedMjpegServer, _stop_both, _wait_until

REPO = Path(__file__).resolve().parents[3]


def _scene(i: int) -> np.ndarray:
    """A 320x240 frame with texture everywhere (no flat grey of its own), different for each i."""
    rng = np.random.default_rng(i)
    img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), (5, 5), 0)
    cv2.putText(img, f"frame {i}", (20, 120), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3)
    return img


def _jpeg(i: int) -> bytes:
    return cv2.imencode(".jpg", _scene(i), [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def test_opencv_fills_a_truncated_jpeg_with_grey_and_the_reader_refuses_it(tmp_path: Path) -> None:
    """What the audit saw: the file cut at 3 % of its bytes reads back as an image, 97 % flat
    grey. ``read_image`` refuses it; whole JPEGs (with padding after the end marker too) pass."""
    data = _jpeg(0)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[: len(data) * 3 // 100])
    partial = cv2.imread(str(cut), cv2.IMREAD_UNCHANGED)
    if partial is not None:  # this OpenCV decodes what is there
        assert (partial == 128).all(axis=2).mean() > 0.9
    assert truncated_jpeg(cut.read_bytes()) and read_image(cut) is None
    for frac in (0.5, 0.99):
        cut.write_bytes(data[: int(len(data) * frac)])
        assert read_image(cut) is None
    cut.write_bytes(data[:-2] + bytes(64))  # the end marker lost, zeros in its place
    assert read_image(cut) is None
    whole = tmp_path / "whole.jpg"
    whole.write_bytes(data + b"\x00" * 16 + b"\r\n")  # padding after the end marker
    assert not truncated_jpeg(whole.read_bytes())
    img = read_image(whole)
    assert img is not None and img.shape == (240, 320, 3)
    assert np.array_equal(img, cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR))
    png = tmp_path / "f.png"
    cv2.imwrite(str(png), _scene(1))
    assert np.array_equal(read_image(png), _scene(1))
    assert decode_image(b"") is None and read_image(tmp_path / "missing.jpg") is None


def test_a_truncated_jpeg_in_a_frames_folder_is_counted_and_dropped(tmp_path: Path) -> None:
    for i in range(4):
        data = _jpeg(i)
        # Frames 1 and 2 were cut short while being written (3 % and 90 % of their bytes).
        cut = {1: len(data) * 3 // 100, 2: len(data) * 9 // 10}.get(i, len(data))
        (tmp_path / f"f{i:03d}.jpg").write_bytes(data[:cut])
    cam = CameraSource(str(tmp_path), fps=200)
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 5)
    cam.stop()
    assert cam.stats.corrupt == 2 and cam.stats.frames == 2
    for frame in got:  # the two whole ones, none of them grey filler
        assert (frame.image == 128).all(axis=2).mean() < 0.05
    assert [int(np.abs(f.image.astype(int) - _scene(i).astype(int)).mean() < 10) for f, i in zip(got, (0, 3))] == [1, 1]


def test_a_truncated_jpeg_part_of_an_mjpeg_stream_is_counted_and_dropped() -> None:
    """A part whose Content-Length matches its bytes, but whose JPEG was cut short upstream."""
    whole = [_jpeg(i) for i in range(3)]

    def script(conn: int):
        yield whole[0]
        yield whole[1][: len(whole[1]) // 2]
        yield whole[2]
        yield None

    server = _ScriptedMjpegServer(script)
    cam = CameraSource(server.url, stall_timeout_s=5.0)
    got = _collect(cam)
    try:
        cam.start()
        assert _wait_until(lambda: cam.stats.frames + cam.stats.corrupt >= 3, 5)
    finally:
        _stop_both(cam, server)
    assert cam.stats.corrupt == 1 and cam.stats.frames == 2 and len(got) == 2


def _undecodable_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        data = _jpeg(i)
        (folder / f"f{i:03d}.jpg").write_bytes(data[: len(data) // 3])
    (folder / "f003.png").write_bytes(b"not a png at all")
    return folder


@early.batch("undecodable-folder")
def _undecodable_folder_start_ups(folder: Path) -> list[early.Run]:
    """``check-config`` and ``run`` of a folder where no image decodes: each starts a Python and
    loads onnxruntime, so they start side by side once the session knows it runs the test."""
    frames = _undecodable_folder(folder)
    from tests.conftest import MODEL as model  # the fixture model_path's
    cfg = folder / "companion.toml"
    cfg.write_text(f'[camera]\nsource = "{frames}"\n[model]\npath = "{model}"\n')
    return [early.Run([sys.executable, "-m", "companion", *args], REPO)
            for args in (["check-config", str(cfg)], ["run", "--camera", str(frames), "--model", str(model)])]


@pytest.mark.started_early("undecodable-folder")
def test_a_frames_folder_where_no_image_decodes_is_refused_at_start_up(tmp_path: Path, model_path: Path) -> None:
    folder = _undecodable_folder(tmp_path)
    with pytest.raises(CameraError, match="none of the folder's 4 image file"):
        check_source(str(folder))
    # One whole image among them is enough to start (the others are counted as they play).
    (folder / "f004.jpg").write_bytes(_jpeg(4))
    check_source(str(folder))
    # check-config and run of such a folder (one of its own, tests/early.py): exit 2 naming it.
    folder, runs = early.result("undecodable-folder")
    folder = folder / "frames"
    assert runs[1].args[-1] == str(model_path)  # run --model, as the config's model.path
    for r in runs:
        args = r.args
        assert r.returncode == 2, (args, r.stderr)
        assert str(folder) in r.stderr and "decodes" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr
