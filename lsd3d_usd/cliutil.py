"""Small parsers and checks shared by the command modules."""
from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import check_image_size

_SIZE = re.compile(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*")


def _parse_wh(text, flag: str, width_only: bool, minimum: int) -> tuple[int, int | None]:
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


def parse_size(text: str | None, flag: str = "--resolution", *, width_only: bool = False,
               minimum: int = 1, max_pixels: int | None = None) -> tuple[int, int | None] | None:
    """'WxH' → (W, H); with width_only also 'W' → (W, None). None passes through.
    Raises InputError naming the flag; sizes above ``max_pixels`` (default
    limits.IMAGE_PIXELS; a width alone counts as one row) are refused before anything
    is allocated."""

    if text is None:
        return None
    w, h = _parse_wh(text, flag, width_only, minimum)
    check_image_size(w, h if h is not None else 1, flag, max_pixels)
    return w, h


def size_type(flag: str, minimum: int = 1):
    """argparse `type=` for WxH values: a malformed value is argparse's usual error. The
    pixel limit is left to the command (limits.check_image_size), whose error is one line."""

    def parse(text):
        try:
            return _parse_wh(text, flag, False, minimum)
        except InputError as e:
            raise argparse.ArgumentTypeError(str(e).split(": ", 1)[1]) from None
    return parse


# ----------------------------------------------------------------- output paths
def check_output_path(path, flag: str = "-o", *, suffixes: tuple[str, ...] | None = None,
                      what: str = "output file") -> Path:
    """Refuse, before any work, an output path that cannot become a file: an existing
    folder (or a path ending in a separator), or one below an existing file. With
    ``suffixes``, the extension must be one of them. Returns the path."""
    text = os.fspath(path)
    p = Path(text)
    if text.endswith(("/", os.sep)) or p.is_dir():
        raise InputError(f"{flag} {text}: is a folder; give the {what}'s name")
    for parent in p.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{flag} {text}: {parent} is a file, not a folder")
            break
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise InputError(f"{flag} {text}: the {what} must end in "
                         f"{' or '.join(suffixes)}")
    return p


def check_output_folder(path, flag: str = "-o", *, scene=None) -> Path:
    """Refuse, before any work, an output folder that is an existing file, lies below a
    file, or is (or lies inside, or holds) the ``scene`` folder: frames written there would
    replace the scene's own files. Returns the path."""
    text = os.fspath(path)
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise InputError(f"{flag} {text}: exists and is not a folder")
    for parent in p.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{flag} {text}: {parent} is a file, not a folder")
            break
    if scene is not None:
        sc = Path(scene)
        sc = (sc if sc.is_dir() else sc.parent).resolve()
        o = p.resolve()
        if o == sc or o.is_relative_to(sc):
            raise InputError(f"{flag} {text}: inside the scene folder {sc}; write the frames "
                             "elsewhere (a scene folder holds only the scene)")
        if sc.is_relative_to(o):
            raise InputError(f"{flag} {text}: the scene {sc} lies inside it; write the frames "
                             "elsewhere")
    return p


# --------------------------------------------------------------------- argparse
def accept_negative_values(parser) -> None:
    """Let option values that start with '-' and a digit ('-1,0', '-2.5e3') be values,
    not unknown options, as Python 3.13's argparse does. Call on the (sub)parser that
    owns such options."""
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = re.compile(r"^-\.?\d")


def add_limit_option(parser, limit, type=int) -> None:
    """A ``limit.flag`` option (e.g. --max-chunks N) that raises one limits.Limit for this
    command; ``args.<dest>`` is None unless given (the library then uses the default)."""

    def positive(text):
        try:
            v = type(float(text)) if type is int else type(text)
        except (TypeError, ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
        return v

    default = int(limit.value) if type is int else limit.value
    parser.add_argument(limit.flag, type=positive, default=None, metavar="N",
                        help=f"raise the limit on the {limit.what} (default {default}{limit.unit}; "
                             "docs/limits.md)")
