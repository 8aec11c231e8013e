"""Small parsers shared by the command modules."""
from __future__ import annotations

import re

from lsd3d_usd.errors import InputError

_SIZE = re.compile(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*")


def parse_size(text: str | None, flag: str = "--resolution", *, width_only: bool = False,
               minimum: int = 1) -> tuple[int, int | None] | None:
    """'WxH' → (W, H); with width_only also 'W' → (W, None). None passes through.
    Raises InputError naming the flag."""
    if text is None:
        return None
    m = _SIZE.fullmatch(str(text))
    ok = m is not None and (m.group(2) is not None or width_only)
    if ok:
        w, h = int(m.group(1)), (int(m.group(2)) if m.group(2) else None)
        ok = w >= minimum and (h is None or h >= minimum)
    if not ok:
        form = "WIDTHxHEIGHT (e.g. 960x540)" + (" or WIDTH" if width_only else "")
        limit = f", each at least {minimum}" if minimum > 1 else ""
        raise InputError(f"{flag} {text!r}: use {form}{limit}")
    return w, h


def size_type(flag: str, minimum: int = 1):
    """argparse `type=` for WxH values: a bad value is argparse's usual one-line error."""
    import argparse

    def parse(text):
        try:
            return parse_size(text, flag, minimum=minimum)
        except InputError as e:
            raise argparse.ArgumentTypeError(str(e).split(": ", 1)[1]) from None
    return parse


def check_output_file(path, flag: str) -> None:
    """An output file path that can be written: its folder exists and it is not a folder.
    Checked before long work, so a bad path fails at once rather than after the run."""
    from pathlib import Path
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{flag} {path}: is a folder, not a file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        what = "is a file" if parent.exists() else "does not exist"
        raise InputError(f"{flag} {path}: its folder {parent} {what}")
