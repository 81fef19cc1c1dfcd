"""Calls a module-level function with JSON arguments and writes what it returns, pickled, to a
file (written whole: a test that sees the file sees all of it): the command of
``tests.early.call``, run by tests/early_runner.py beside the tests.

Usage: python -m tests.early_call OUT MODULE:FUNCTION ARGS.json
"""

from __future__ import annotations

import importlib
import json
import os
import pickle
import sys


def main(out: str, target: str, args: str) -> int:
    module, name = target.split(":")
    value = getattr(importlib.import_module(module), name)(*json.loads(args))
    with open(out + ".tmp", "wb") as f:
        pickle.dump(value, f)
    os.replace(out + ".tmp", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:]))
