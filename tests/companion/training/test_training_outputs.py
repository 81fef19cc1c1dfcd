"""The training commands never write into a shipped model unless told to: the file a command
rewrites or creates is named on its command line (exit 2 without it), and quantize reads the
service's default model when none is named."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from companion.config import SHIPPED_MODEL

MODELS = Path(SHIPPED_MODEL).parent


def _digests() -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(MODELS.glob("*.onnx"))}


def _exit_code(main, argv: list[str]) -> int:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return int(exc.value.code)


def test_calibrate_needs_the_model_it_rewrites(tmp_path: Path, capsys) -> None:
    from companion.training.calibrate import main

    before = _digests()
    assert _exit_code(main, ["--shared", str(tmp_path)]) == 2
    assert "--model" in capsys.readouterr().err
    assert _digests() == before


def test_train_and_landability_need_the_file_they_write(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.landability import main as landability_main
    from companion.training.train import main as train_main

    before = _digests()
    for main in (train_main, landability_main):
        assert _exit_code(main, ["--shared", str(tmp_path)]) == 2
        assert "--out" in capsys.readouterr().err
    assert _digests() == before


def test_quantize_reads_the_services_default_model_when_none_is_named() -> None:
    pytest.importorskip("onnx", reason="quantize needs onnx (the 'train' extra)")
    from companion.training.quantize import build_parser

    args = build_parser().parse_args(["--out", "x.onnx"])
    assert Path(args.model) == Path(SHIPPED_MODEL) and Path(args.model).is_file()
