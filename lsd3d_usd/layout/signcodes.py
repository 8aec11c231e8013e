"""Road-sign codes of the map formats → what the layout keeps of a sign.

Maps name signs by national catalogue codes: OpenDRIVE ``country`` + ``type`` (+ ``subtype``),
Lanelet2 sign subtypes (``de205``), OpenStreetMap ``traffic_sign=DE:205``. ``sign_kind``
reads the German StVO and US MUTCD numbering (the catalogues OpenDRIVE and Lanelet2 maps
use most) and a few words; anything else is ``other``. ``stop`` and ``traffic_light`` are
not TrafficSign kinds: importers make a StopSign or TrafficLight of them.
"""
from __future__ import annotations

import re

_NUM = re.compile(r"(\d+)")


def split_code(code: str) -> tuple[str, str]:
    """(country, sign) of a code such as ``DE:205``, ``de205``, ``US:R1-2``, ``274.1``."""
    c = str(code or "").strip()
    if ":" in c:
        country, sign = c.split(":", 1)
        return country.strip().upper(), sign.strip()
    mt = re.match(r"^([A-Za-z]{2})(\d.*)$", c)      # lanelet2 style: de205, de274-50
    if mt:
        return mt.group(1).upper(), mt.group(2)
    return "", c


def sign_kind(country: str, sign: str, name: str = "") -> str:
    """One of model.SIGN_KINDS, or ``stop`` / ``traffic_light``, for a sign of ``country``'s
    catalogue (ISO code such as DE or US, or empty: then the number is read as StVO)."""
    country = (country or "").upper()
    s = str(sign or "").strip().upper()
    words = f"{s} {name}".lower()
    if s.startswith("R1-1") or "stop" in words.split() or s == "STOP":
        return "stop"
    if s.startswith("R1-2") or "yield" in words or "give_way" in words or "giveway" in words:
        return "yield"
    if s.startswith("R2-1") or "maxspeed" in words or "speed" in words:
        return "speed_limit"
    if s.startswith("R5-1") or "no_entry" in words:
        return "no_entry"
    if country == "US" or re.match(r"^[A-Z]\d", s):
        head = s[:1]
        return {"R": "prohibition", "W": "warning", "D": "information", "I": "information",
                "M": "information", "S": "warning"}.get(head, "other")
    mt = _NUM.match(s)
    if not mt:
        return "other"
    n = int(mt.group(1))
    if 1_000_000 <= n < 1_100_000:          # StVO 1000001 ... : traffic lights
        return "traffic_light"
    if n == 206:
        return "stop"
    if n == 205:
        return "yield"
    if n in (301, 306, 308):
        return "priority"
    if n == 267:
        return "no_entry"
    if n == 274:
        return "speed_limit"
    if 101 <= n <= 157:
        return "warning"
    if 209 <= n <= 245:
        return "mandatory"
    if 250 <= n <= 299:
        return "prohibition"
    if 300 <= n <= 499:
        return "information"
    return "other"
