"""Motion-JPEG AVI from JPEG bytes (companion.avi), read back by OpenCV and by the chunk walker."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.avi import MjpegAviWriter, _chunk, encode_jpeg, is_jpeg, jpeg_frames


def _frame(i: int, w: int = 160, h: int = 120) -> np.ndarray:
    rng = np.random.default_rng(i)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2)
    cv2.putText(img, str(i), (10, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3)
    return img


def _decode(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def _write(path: Path, jpegs: list[bytes], close: bool = True, fps: float = 12.5) -> MjpegAviWriter:
    w = MjpegAviWriter(path, (160, 120), fps)
    for j in jpegs:
        w.write(j)
    if close:
        w.close()
    else:
        assert w._fh is not None
        w._fh.flush()  # what a power cut leaves: the frames, not the sizes nor the index
    return w


def _opencv_frames(path: Path) -> tuple[list[np.ndarray], cv2.VideoCapture]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while cap.isOpened():
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    return out, cap


def test_jpeg_bytes_go_in_and_come_out_unchanged_and_opencv_plays_the_file(tmp_path: Path) -> None:
    # Odd and even lengths (the pad byte), quality 60 and 95.
    jpegs = [encode_jpeg(_frame(i), 60 + 35 * (i % 2)) for i in range(9)]
    assert any(len(j) % 2 for j in jpegs) and any(len(j) % 2 == 0 for j in jpegs)
    path = tmp_path / "seg.avi"
    w = _write(path, jpegs)
    assert w.frames == 9
    w.close()  # twice: a no-op
    assert list(jpeg_frames(path)) == jpegs
    frames, cap = _opencv_frames(path)
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 9
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(12.5)
    assert len(frames) == 9
    for img, j in zip(frames, jpegs, strict=True):
        # FFmpeg's decoder is not libjpeg's: close, not equal.
        assert img.shape == (120, 160, 3)
        assert float(np.abs(img.astype(int) - _decode(j)).mean()) < 3


def test_a_file_cut_off_before_it_was_closed_reads_up_to_its_last_whole_frame(tmp_path: Path) -> None:
    jpegs = [encode_jpeg(_frame(i)) for i in range(8)]
    path = tmp_path / "cut.avi"
    _write(path, jpegs, close=False)
    data = path.read_bytes()
    assert list(jpeg_frames(path)) == jpegs  # never closed, nothing lost: no index needed
    cut = data[: len(data) - len(jpegs[-1]) // 2]  # the power cut lands in the last frame
    path.write_bytes(cut)
    assert list(jpeg_frames(path)) == jpegs[:-1]
    frames, _ = _opencv_frames(path)
    assert len(frames) >= 7


def test_opencv_mjpg_files_of_older_recordings_give_their_jpegs(tmp_path: Path) -> None:
    path = tmp_path / "old.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))  # type: ignore[attr-defined]
    for i in range(5):
        vw.write(_frame(i))
    vw.release()
    got = list(jpeg_frames(path))
    assert len(got) == 5 and all(is_jpeg(j) for j in got)
    frames, _ = _opencv_frames(path)
    for img, j in zip(frames, got, strict=True):
        assert float(np.abs(img.astype(int) - _decode(j)).mean()) < 3


def test_frames_in_an_opendml_continuation_are_read_too(tmp_path: Path) -> None:
    # Past 1 GiB a writer goes on in a RIFF 'AVIX' with its own movi list; ours never gets there
    # (segments end at 64 MiB), but a reader of other files must not stop at the first.
    jpegs = [encode_jpeg(_frame(i)) for i in range(4)]
    path = tmp_path / "big.avi"
    _write(path, jpegs[:2])
    movi = b"movi" + b"".join(_chunk(b"00dc", j) for j in jpegs[2:])
    avix = b"AVIX" + b"LIST" + len(movi).to_bytes(4, "little") + movi
    with open(path, "ab") as fh:
        fh.write(b"RIFF" + len(avix).to_bytes(4, "little") + avix)
    assert list(jpeg_frames(path)) == jpegs


def test_what_is_not_an_mjpg_avi_is_refused_before_any_frame(tmp_path: Path) -> None:
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="not an AVI"):
        next(jpeg_frames(junk))
    other = tmp_path / "other.avi"
    data = bytearray(_write(tmp_path / "x.avi", [encode_jpeg(_frame(0))]).path.read_bytes())
    at = data.find(b"strf") + 8 + 16
    data[at:at + 4] = b"XVID"  # the stream's format says another codec
    other.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="not MJPG"):
        next(jpeg_frames(other))


def test_the_writer_refuses_what_it_cannot_store(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="positive size"):
        MjpegAviWriter(tmp_path / "a.avi", (0, 120), 10)
    for fps in (0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="positive size"):
            MjpegAviWriter(tmp_path / "b.avi", (160, 120), fps)
    w = MjpegAviWriter(tmp_path / "c.avi", (160, 120), 10)
    with pytest.raises(ValueError, match="not JPEG"):
        w.write(cv2.imencode(".png", _frame(0))[1].tobytes())
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write(encode_jpeg(_frame(0)))
    assert list(jpeg_frames(tmp_path / "c.avi")) == []
