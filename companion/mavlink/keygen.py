"""``companion signing-key``: make a MAVLink 2 signing key for the companion and the autopilot.

The key is the SHA-256 of a random passphrase, as MAVProxy's ``signing setup PASSPHRASE`` makes
it, so the same passphrase provisions the autopilot (ArduPilot, and PX4 from v1.15 through the
standard SETUP_SIGNING message MAVProxy sends) and the file written here holds the same key for
the companion (``link.signing_key_file``). The file is created with mode 0600 and never
overwritten; the passphrase is printed once and stored nowhere. docs/signing.md has the steps.
"""

from __future__ import annotations

import argparse
import os
import secrets
import sys
from pathlib import Path

from companion.mavlink.link import parse_signing_key


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="key file to create (64 hex characters, mode 0600; refused if it exists)")


def run(args: argparse.Namespace) -> int:
    passphrase = secrets.token_urlsafe(24)
    key = parse_signing_key(passphrase)
    try:
        fd = os.open(args.out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        print(f"companion signing-key: cannot create {args.out}: {exc.strerror}", file=sys.stderr)
        return 2
    with os.fdopen(fd, "w") as fh:
        fh.write(key.hex() + "\n")
    print(f"key written to {args.out} (mode 0600): set link.signing_key_file = \"{args.out}\" and "
          "link.require_signing = true")
    print("provision the autopilot over a trusted link (USB), in MAVProxy:")
    print(f"  signing setup {passphrase}")
    print("this passphrase is not stored anywhere: keep it in your secrets store or make a new key")
    return 0
