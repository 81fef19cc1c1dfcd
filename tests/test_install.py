"""Installing like companion software: a wheel that works from anywhere, ``--version``,
``check-config``, a clean ``--help``, and a clear message when an optional extra is missing.

The wheel test builds the wheel from a copy of the source tree (so no stale ``build/`` of the
clone can leak into it), installs it into a fresh virtual environment outside the clone, and runs
the installed ``companion`` from a temporary directory. The third-party dependencies are those of
the test's own environment, reached through a ``.pth`` line placed after the fresh environment's
own site-packages, so the installed ``companion`` is the one imported, not the clone's.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from dataclasses import replace
from pathlib import Path

import pytest

from companion import __version__
from companion import config as config_mod
from companion.cli import build_parser, command_names

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "companion.example.toml"

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def _companion(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=120)


def _side_by_side(argvs: list[list[str]], cwd: Path | list[Path] | None = None,
                  env: dict[str, str] | None = None) -> list[subprocess.CompletedProcess[str]]:
    """Each command of ``argvs`` started at once and waited for, in order (each starts a Python
    and imports the package: side by side they take the time of about one or two, not of all).
    ``cwd``: one folder for all, or one per command."""
    cwds = cwd if isinstance(cwd, list) else [cwd] * len(argvs)
    procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=where, env=env)
             for argv, where in zip(argvs, cwds, strict=True)]
    done = []
    for argv, proc in zip(argvs, procs, strict=True):
        out, err = proc.communicate(timeout=120)
        done.append(subprocess.CompletedProcess(argv, proc.returncode, out, err))
    return done


def _companions(*argss: tuple[str, ...], cwd: Path | None = None) -> list[subprocess.CompletedProcess[str]]:
    return _side_by_side([[sys.executable, "-m", "companion", *args] for args in argss], cwd=cwd)


# ---- check-config ---------------------------------------------------------------------------

def test_the_settings_load_without_the_kalman_filters_statistics() -> None:
    # filterpy's package imports scipy.stats (about 0.8 s): every command paid it through
    # companion.config before it could say a key was wrong. The zone tracker imports it when
    # made (the service at start-up), and its filters work as before.
    code = ("import sys, companion.config, companion.cli\n"
            "print('filterpy' in sys.modules, 'scipy.stats' in sys.modules)\n"
            "from companion.pipeline.tracker import ZoneTracker\n"
            "from companion.pipeline.circles import Circle\n"
            "tr = ZoneTracker()\n"
            "print('filterpy' in sys.modules)\n"
            "for k in range(5): tr.update([Circle(1.0, 2.0, 3.0)], k * 0.1)\n"
            "print(len(tr.update([Circle(1.0, 2.0, 3.0)], 0.5)))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False", "True", "1"], r.stdout


def test_check_config_accepts_the_example_and_prints_what_it_resolves_to(tmp_path: Path) -> None:
    r = _companion("check-config", str(EXAMPLE), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    resolved = tomllib.loads(r.stdout)  # the printout is TOML itself
    # Every key, each with the value run would use: the example's empty model.path is the shipped model.
    flat = {key for key, _default, _doc in config_mod.all_keys()}
    printed = set()
    for section, table in resolved.items():
        for key, value in table.items():
            if isinstance(value, dict) and f"{section}.{key}" not in flat:
                printed |= {f"{section}.{key}.{k}" for k in value}
            else:
                printed.add(f"{section}.{key}")
    assert printed == flat
    assert Path(resolved["model"]["path"]) == config_mod.SHIPPED_MODEL
    assert config_mod.SHIPPED_MODEL.is_file()
    assert config_mod.from_dict(resolved) == replace(config_mod.load(EXAMPLE), source=None)


BAD_CONFIGS = [
    ("[camera]\nfsp = 10\n", "camera.fsp"),                # a wrong key
    ("[camera]\nfps = -3\n", "camera.fps"),                # a wrong value
    ("[link]\nurl = \"udpin:127.0.0.1:99999\"\n", "link.url"),
    ("[model]\npath = \"no-such-model.onnx\"\n", "model.path"),  # the model is loaded, not just named
    ("[controller]\nhold_looks = false\n", "controller.hold_looks was removed"),  # issue 58: says so
]


@pytest.fixture(scope="module")
def bad_config_checks(tmp_path_factory: pytest.TempPathFactory) -> dict[str, subprocess.CompletedProcess[str]]:
    """``companion check-config`` of each of BAD_CONFIGS (its own file in its own folder), the
    commands started at once: the text -> what the command did."""
    folders = []
    for text, _key in BAD_CONFIGS:
        folder = tmp_path_factory.mktemp("bad_config")
        (folder / "c.toml").write_text(text)
        folders.append(folder)
    runs = _side_by_side([[sys.executable, "-m", "companion", "check-config", str(folder / "c.toml")]
                          for folder in folders], cwd=folders)
    return {text: r for (text, _key), r in zip(BAD_CONFIGS, runs, strict=True)}


@pytest.mark.parametrize(("text", "key"), BAD_CONFIGS)
def test_check_config_exits_2_naming_the_key(bad_config_checks: dict[str, subprocess.CompletedProcess[str]],
                                             text: str, key: str) -> None:
    r = bad_config_checks[text]
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert key in r.stderr and "Traceback" not in r.stderr
    assert r.stdout == ""


def test_check_config_exits_2_on_a_malformed_model(tmp_path: Path) -> None:
    (tmp_path / "bad.onnx").write_bytes(b"not an onnx model at all")
    f = tmp_path / "c.toml"
    f.write_text('[model]\npath = "bad.onnx"\n')
    r = _companion("check-config", str(f), cwd=tmp_path)
    assert r.returncode == 2 and "model.path" in r.stderr and "Traceback" not in r.stderr


def test_check_config_exits_2_on_malformed_toml_and_a_missing_file(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[camera\nfps = 10\n")
    r, missing = _companions(("check-config", str(f)), ("check-config", str(tmp_path / "missing.toml")), cwd=tmp_path)
    assert r.returncode == 2 and "not valid TOML" in r.stderr and str(f) in r.stderr
    r = missing
    assert r.returncode == 2 and "does not exist" in r.stderr and "missing.toml" in r.stderr


def test_check_config_takes_set_overrides_as_run_does(tmp_path: Path) -> None:
    r, bad = _companions(("check-config", str(EXAMPLE), "--set", "camera.fps=15"),
                         ("check-config", str(EXAMPLE), "--set", "camera.fps=0"), cwd=tmp_path)
    assert r.returncode == 0 and tomllib.loads(r.stdout)["camera"]["fps"] == 15.0
    r = bad
    assert r.returncode == 2 and "camera.fps" in r.stderr


# ---- --version, --help, missing extras -------------------------------------------------------

def test_version_is_the_packages() -> None:
    r = _companion("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"companion {__version__}"


@pytest.mark.parametrize("command", [None, *command_names()])
def test_help_shows_no_restructuredtext(command: str | None) -> None:
    parser, _module = build_parser(command)
    if command is not None:
        parser = next(a for a in parser._actions if a.dest == "command").choices[command]  # type: ignore[union-attr]
    text = parser.format_help()
    assert "``" not in text and ":class:" not in text and ":func:" not in text, text
    assert parser.description and not parser.description.startswith(" ")


def test_a_missing_optional_package_names_its_extra(tmp_path: Path) -> None:
    # sys.modules[name] = None makes the import fail exactly as an absent package does. A replay
    # without a progress bar needs no tqdm (the container image has none); one with it does.
    import cv2
    import numpy as np
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "000.png"), np.full((48, 64, 3), 90, np.uint8))
    codes = [("import sys; sys.modules['tqdm'] = None; from companion.cli import main; "
              f"sys.exit(main({argv!r}))")
             for argv in (["replay", "--help"], ["replay", str(frames), "--nadir", "--gsd", "0.05", "--progress"],
                          ["sim-scenarios", "--seeds", "1-3", "--json"])]
    r, *runs = _side_by_side([[sys.executable, "-c", code] for code in codes], cwd=tmp_path)
    assert "Traceback" not in r.stderr
    for r in runs:
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "pip install 'companion-slz[tools]'" in r.stderr and "tqdm" in r.stderr, r.stderr


def test_the_demo_without_pyav_says_so_before_flying(tmp_path: Path) -> None:
    code = ("import sys; sys.modules['av'] = None; from companion.cli import main; "
            f"sys.exit(main(['demo', '--out', {str(tmp_path / 'out')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode == 2 and "companion-slz[tools]" in r.stderr and "--no-video" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()  # nothing flown, nothing written


# ---- the wheel, installed outside the clone --------------------------------------------------

def _dockerfile() -> list[tuple[str, list[str]]]:
    """The Dockerfile's instructions as (INSTRUCTION, arguments), continuation lines joined."""
    text = re.sub(r"\\\n", " ", (REPO / "Dockerfile").read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.split()))
    return out


def _build_stage_copies() -> list[tuple[str, str]]:
    """(source, destination) of each COPY of the Dockerfile's first stage, the one building the wheel."""
    copies, stage = [], 0
    for word, args in _dockerfile():
        if word == "FROM":
            stage += 1
        elif word == "COPY" and stage == 1:
            *sources, dest = args
            copies += [(src, dest) for src in sources]
    return copies


def _copy_source(dest: Path) -> Path:
    """What the Dockerfile's build stage copies, laid out as it lays it out (so the wheel this
    test installs is the one the image installs)."""
    dest.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    for src, to in _build_stage_copies():
        target = dest / to if not to.endswith("/") and to not in ("./", ".") else dest / Path(src).name
        if (REPO / src).is_dir():
            shutil.copytree(REPO / src, target, ignore=ignore)
        else:
            shutil.copy(REPO / src, target)
    return dest


def test_the_dockerfile_copies_what_exists_and_runs_the_service() -> None:
    ignored = [line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")]
    steps = _dockerfile()
    copies = [args for word, args in steps if word == "COPY" and not args[0].startswith("--from")]
    assert copies
    for *sources, _dest in copies:
        for src in sources:
            assert (REPO / src).exists(), f"the Dockerfile copies {src}, which is not in the repository"
            assert not any(fnmatch.fnmatch(src.rstrip("/"), pat.strip("/")) for pat in ignored), \
                f"{src} is copied but .dockerignore leaves it out of the build context"
    assert sum(word == "FROM" for word, _ in steps) == 2  # multi-stage: build the wheel, then install it
    assert any(word == "USER" and args != ["root"] for word, args in steps)
    (entry,) = [args for word, args in steps if word == "ENTRYPOINT"]
    argv = json.loads(" ".join(entry))
    assert argv[:2] == ["companion", "run"] and argv[2:] == ["--config", "/etc/companion/companion.toml"]
    assert ["companion.example.toml", "/etc/companion/companion.toml"] in copies  # the config it names exists
    assert any("pip wheel" in " ".join(args) and "--no-deps" in args for word, args in steps if word == "RUN")


def test_a_wheel_installed_outside_the_clone_runs_and_finds_its_model(tmp_path: Path) -> None:
    src = _copy_source(tmp_path / "src")
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(dist)],
                   check=True, capture_output=True, text=True, timeout=300)
    (wheel,) = dist.glob("companion_slz-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {"companion/models/slz-density-v5.onnx", "companion/models/slz-density-v4.onnx", "companion/models/slz-density-v4-x86.onnx",
            "companion/models/slz-density.onnx"} <= set(names) and "companion/models/MODEL_CARD.md" in names

    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=False, symlinks=True)
    py = env_dir / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q",
                    str(wheel)], check=True, capture_output=True, text=True, timeout=300)
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # The dependencies (numpy, onnxruntime, ...) from this test's environment, after the wheel's own
    # files: a plain path line, so the editable install's finder there is not loaded.
    (site / "zz_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    run_dir = tmp_path / "elsewhere"
    run_dir.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    companion = env_dir / "bin" / "companion"

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(args, capture_output=True, text=True, cwd=run_dir, env=env, timeout=120)

    r = run(str(py), "-c", "import companion, sim; print(companion.__file__); print(sim.__file__)")
    assert r.returncode == 0, r.stderr
    assert all(Path(line).is_relative_to(site) for line in r.stdout.split()), r.stdout

    example = run_dir / "companion.toml"
    shutil.copy(EXAMPLE, example)  # as docs/install.md copies it to /etc/companion
    r, demo_help, check = _side_by_side([[str(companion), "--version"], [str(companion), "demo", "--help"],
                                         [str(companion), "check-config", str(example)]], cwd=run_dir, env=env)
    assert r.returncode == 0 and r.stdout.strip() == f"companion {__version__}"
    r = demo_help
    assert r.returncode == 0 and "--flavour" in r.stdout, r.stderr

    r = check
    assert r.returncode == 0, r.stderr
    model = Path(tomllib.loads(r.stdout)["model"]["path"])
    assert model.is_relative_to(site) and model.is_file() and model.stat().st_size > 100_000
    assert re.search(r"^threads = 2$", r.stdout, re.M)


def test_the_container_build_script_parses_and_checks_what_the_image_holds() -> None:
    """scripts/container-build.sh (docs/install.md, "Container") builds the image from Debian's
    packages with debootstrap and buildah; building takes minutes and root, so CI only parses it
    and checks that the replay it runs inside the image uses options `companion replay` has."""
    script = REPO / "scripts" / "container-build.sh"
    r = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = script.read_text()
    assert "debootstrap" in text and "buildah bud" in text and "BASE_IMAGE=" in text
    from companion.replay.cli import configure
    parser = argparse.ArgumentParser()
    configure(parser)
    args = parser.parse_args(["frames", "--nadir", "--gsd", "0.05", "--no-progress",
                                      "--summary-json", "summary.json"])
    assert args.nadir and args.gsd == 0.05
    assert "companion replay frames --nadir --gsd 0.05 --no-progress --summary-json summary.json" in text
