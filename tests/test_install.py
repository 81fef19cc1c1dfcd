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
import shlex
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from dataclasses import replace
from pathlib import Path

import pytest

from companion import __version__
from companion import config as config_mod
from companion.cli import build_parser, command_names
from tests import early

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


def _companion_run(*args: str, cwd: Path) -> early.Run:
    """``companion ARGS`` in ``cwd``, as a command of an early batch (tests/early.py): the
    commands of this module's tests each start a Python and import the package, and start when
    the session knows it runs the test, beside the tests before it."""
    return early.Run([sys.executable, "-m", "companion", *args], cwd)


# ---- check-config ---------------------------------------------------------------------------

@early.batch("settings-without-filterpy")
def _settings_without_filterpy(folder: Path) -> list[early.Run]:
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
    return [early.Run([sys.executable, "-c", code], folder)]


@pytest.mark.started_early("settings-without-filterpy")
def test_the_settings_load_without_the_kalman_filters_statistics() -> None:
    (r,) = early.result("settings-without-filterpy")[1]
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False", "True", "1"], r.stdout


@early.batch("check-config-example")
def _check_config_example(folder: Path) -> list[early.Run]:
    return [_companion_run("check-config", str(EXAMPLE), cwd=folder)]


@pytest.mark.started_early("check-config-example")
def test_check_config_accepts_the_example_and_prints_what_it_resolves_to() -> None:
    (r,) = early.result("check-config-example")[1]
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


@early.batch("bad-configs")
def _bad_configs(folder: Path) -> list[early.Run]:
    """``companion check-config`` of each of BAD_CONFIGS, its own file in its own folder."""
    runs = []
    for k, (text, _key) in enumerate(BAD_CONFIGS):
        (folder / str(k)).mkdir()
        (folder / str(k) / "c.toml").write_text(text)
        runs.append(_companion_run("check-config", str(folder / str(k) / "c.toml"), cwd=folder / str(k)))
    return runs


@pytest.fixture(scope="module")
def bad_config_checks() -> dict[str, subprocess.CompletedProcess[str]]:
    """What ``companion check-config`` did with each of BAD_CONFIGS: the text -> the run."""
    runs = early.result("bad-configs")[1]
    return {text: r for (text, _key), r in zip(BAD_CONFIGS, runs, strict=True)}


@pytest.mark.started_early("bad-configs")
@pytest.mark.parametrize(("text", "key"), BAD_CONFIGS)
def test_check_config_exits_2_naming_the_key(bad_config_checks: dict[str, subprocess.CompletedProcess[str]],
                                             text: str, key: str) -> None:
    r = bad_config_checks[text]
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert key in r.stderr and "Traceback" not in r.stderr
    assert r.stdout == ""


@early.batch("malformed-model")
def _malformed_model(folder: Path) -> list[early.Run]:
    (folder / "bad.onnx").write_bytes(b"not an onnx model at all")
    f = folder / "c.toml"
    f.write_text('[model]\npath = "bad.onnx"\n')
    return [_companion_run("check-config", str(f), cwd=folder)]


@pytest.mark.started_early("malformed-model")
def test_check_config_exits_2_on_a_malformed_model() -> None:
    (r,) = early.result("malformed-model")[1]
    assert r.returncode == 2 and "model.path" in r.stderr and "Traceback" not in r.stderr


@early.batch("malformed-toml")
def _malformed_toml(folder: Path) -> list[early.Run]:
    f = folder / "c.toml"
    f.write_text("[camera\nfps = 10\n")
    return [_companion_run("check-config", str(f), cwd=folder),
            _companion_run("check-config", str(folder / "missing.toml"), cwd=folder)]


@pytest.mark.started_early("malformed-toml")
def test_check_config_exits_2_on_malformed_toml_and_a_missing_file() -> None:
    folder, (r, missing) = early.result("malformed-toml")
    f = folder / "c.toml"
    assert r.returncode == 2 and "not valid TOML" in r.stderr and str(f) in r.stderr
    r = missing
    assert r.returncode == 2 and "does not exist" in r.stderr and "missing.toml" in r.stderr


@early.batch("set-overrides")
def _set_overrides(folder: Path) -> list[early.Run]:
    return [_companion_run("check-config", str(EXAMPLE), "--set", "camera.fps=15", cwd=folder),
            _companion_run("check-config", str(EXAMPLE), "--set", "camera.fps=0", cwd=folder)]


@pytest.mark.started_early("set-overrides")
def test_check_config_takes_set_overrides_as_run_does() -> None:
    r, bad = early.result("set-overrides")[1]
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


@early.batch("without-tqdm")
def _without_tqdm(folder: Path) -> list[early.Run]:
    # sys.modules[name] = None makes the import fail exactly as an absent package does. A replay
    # without a progress bar needs no tqdm (the container image has none); one with it does.
    import cv2
    import numpy as np
    frames = folder / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "000.png"), np.full((48, 64, 3), 90, np.uint8))
    codes = [("import sys; sys.modules['tqdm'] = None; from companion.cli import main; "
              f"sys.exit(main({argv!r}))")
             for argv in (["replay", "--help"], ["replay", str(frames), "--nadir", "--gsd", "0.05", "--progress"],
                          ["sim-scenarios", "--seeds", "1-3", "--json"])]
    return [early.Run([sys.executable, "-c", code], folder) for code in codes]


@pytest.mark.started_early("without-tqdm")
def test_a_missing_optional_package_names_its_extra() -> None:
    r, *runs = early.result("without-tqdm")[1]
    assert "Traceback" not in r.stderr
    for r in runs:
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "pip install 'companion-slz[tools]'" in r.stderr and "tqdm" in r.stderr, r.stderr


@early.batch("demo-without-pyav")
def _demo_without_pyav(folder: Path) -> list[early.Run]:
    code = ("import sys; sys.modules['av'] = None; from companion.cli import main; "
            f"sys.exit(main(['demo', '--out', {str(folder / 'out')!r}]))")
    return [early.Run([sys.executable, "-c", code], folder)]


@pytest.mark.started_early("demo-without-pyav")
def test_the_demo_without_pyav_says_so_before_flying() -> None:
    folder, (r,) = early.result("demo-without-pyav")
    assert r.returncode == 2 and "companion-slz[tools]" in r.stderr and "--no-video" in r.stderr, r.stderr
    assert not (folder / "out").exists()  # nothing flown, nothing written


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


@early.batch("wheel")
def _wheel(folder: Path) -> list[early.Run]:
    """The wheel built from a copy of the source, and installed into a fresh virtual environment
    without pip (``venv --without-pip --symlinks``) by this environment's pip: one command, the
    steps in order, stopping at the first that fails."""
    src = _copy_source(folder / "src")
    py = [sys.executable, "-m"]
    steps = [[*py, "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(folder / "dist")],
             [*py, "venv", "--without-pip", "--symlinks", str(folder / "venv")],
             [*py, "pip", "--python", str(folder / "venv" / "bin" / "python"), "install", "--no-deps", "--no-index",
              "-q", "--find-links", str(folder / "dist"), "companion-slz"]]
    return [early.Run(["bash", "-c", " && ".join(shlex.join(step) for step in steps)], folder)]


@pytest.mark.started_early("wheel")
def test_a_wheel_installed_outside_the_clone_runs_and_finds_its_model() -> None:
    tmp_path, (built,) = early.result("wheel")
    assert built.returncode == 0, built.stdout + built.stderr
    (wheel,) = (tmp_path / "dist").glob("companion_slz-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {"companion/models/slz-density-v5.onnx", "companion/models/slz-density-v4.onnx", "companion/models/slz-density-v4-x86.onnx",
            "companion/models/slz-density.onnx"} <= set(names) and "companion/models/MODEL_CARD.md" in names

    env_dir = tmp_path / "venv"
    py = env_dir / "bin" / "python"
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
