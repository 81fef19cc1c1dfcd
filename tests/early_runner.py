"""Runs the commands tests/early.py hands it, one at a time, in the order given: each one's
output to its two files, then its exit status to a third (written whole: a test that sees the
file sees the status). One at a time, so that the test process keeps its core: on two cores the
commands take the other one, beside the tests. Started in a session of its own, so that the
test session can end it and whatever it runs in one go; it ends itself when that session dies.

Usage: python tests/early_runner.py JOBS.json (a list of {argv, cwd, env, out, err, status}).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def main(jobs_file: str) -> int:
    parent = os.getppid()
    for job in json.loads(Path(jobs_file).read_text()):
        if os.getppid() != parent:  # the test session is gone: nobody waits for the rest
            return 1
        with open(job["out"], "w") as out, open(job["err"], "w") as err:
            try:
                code = subprocess.run(job["argv"], cwd=job["cwd"], env=job["env"], stdout=out, stderr=err,
                                      stdin=subprocess.DEVNULL).returncode
            except OSError as exc:  # a tool that is not there: said as a shell would say it
                err.write(f"{exc}\n")
                code = 127
        tmp = Path(job["status"] + ".tmp")
        tmp.write_text(str(code))
        tmp.replace(job["status"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
