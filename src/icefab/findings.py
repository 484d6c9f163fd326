"""Warnings for people: a summary by kind on one screen, the full list in a file.

A build can carry thousands of warnings (a scan's gap closures, one per layer and hole).
Listing the first few hides the rest -- an empty layer's warning fell into "... and 443
more" (issue 11). Instead every kind of warning is summarised once, with its count and the
layers it concerns, and the full list goes in ``COMMAND-warnings.txt`` beside the results
(``slice-warnings.txt``, ``paths-warnings.txt``: each command its own file, so two commands
writing into one folder do not collide; written by the CLI inside its publishing folder,
``icefab.cli.common.output_dir`` / ``write_warnings``).

The kind of a warning is its text without its ``layer K (z = Z mm): `` prefix and with
every number replaced by ``#``: "open contour closed across a # mm gap at (#, #)". The
layer is read from that prefix, which every per-layer warning of ``icefab.slicing`` (and
the valve findings' "layer K ..." of ``icefab.flow``) starts with.
"""

from __future__ import annotations

import re
from typing import Sequence

#: File name of the full list beside the results, after the command's name and a dash
#: (``icefab.cli.common.warnings_file``: ``slice-warnings.txt``).
WARNINGS_FILE = "warnings.txt"

_LAYER = re.compile(r"^layer (\d+)(?: \(z = [^)]*\))?[:,]? ?")
#: A number in a message; not a digit that is part of a word or a unit's power
#: ("cell.l1_mm", "mm^2": "(# mm^# thinner than a path" read badly)
_NUMBER = re.compile(r"(?<![A-Za-z_^])[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def numbers_hidden(text: str) -> str:
    """``text`` with every number replaced by ``#`` (what a kind of message keeps)."""
    return _NUMBER.sub("#", text)


def warning_layer(text: str) -> int | None:
    """The layer a warning names at its start (``layer K ...``), else None."""
    m = _LAYER.match(text)
    return int(m.group(1)) if m else None


def warning_kind(text: str) -> str:
    """The warning without its layer prefix, every number replaced by ``#``."""
    return numbers_hidden(_LAYER.sub("", text, count=1))


def _span(layers: list[int]) -> str:
    if not layers:
        return ""
    if len(layers) == 1:
        return f" (layer {layers[0]})"
    return f" ({len(layers)} layers, {layers[0]}-{layers[-1]})"


def summarise_warnings(warnings: Sequence[str]) -> list[str]:
    """One line per kind: ``"N x <kind> (L layers, a-b)"``, in order of first appearance,
    each number of the kind given as the range it takes (:func:`_ranges`).

    A kind that occurs once is shown as it is (its numbers kept), so a single finding such
    as "layer 153 (z = ...): empty cross-section" keeps its layer in the summary.
    """
    groups: dict[str, list[str]] = {}
    for w in warnings:
        groups.setdefault(warning_kind(w), []).append(w)
    out = []
    for kind, items in groups.items():
        if len(items) == 1:
            out.append(items[0])
            continue
        layers = sorted({k for k in map(warning_layer, items) if k is not None})
        out.append(f"{len(items)} x {_ranges(kind, items)}{_span(layers)}")
    return out


def _ranges(kind: str, items: Sequence[str]) -> str:
    """``kind`` with each ``#`` the range its number takes over ``items`` (warnings of
    that kind): "a" when all give a, else "lo..hi" as the warnings wrote them. A summary
    of ``#`` alone ("part feature narrower than the path width # mm near x = #, y = # mm")
    read like a template left unfilled (a reviewer's)."""
    slots = [[m.group(0) for m in _NUMBER.finditer(_LAYER.sub("", w, count=1))]
             for w in items]
    n = kind.count("#")
    if n == 0 or any(len(v) != n for v in slots):
        return kind
    parts = kind.split("#")
    text = parts[0]
    for k in range(n):
        vals = [v[k] for v in slots]
        lo = min(vals, key=float)
        hi = max(vals, key=float)
        text += (lo if float(lo) == float(hi) else f"{lo}..{hi}") + parts[k + 1]
    return text


_CLAMPED = re.compile(r"clamped \(flow\.out_of_range = 'clamp'\), delivers "
                      r"([-+0-9.eE]+) of ([-+0-9.eE]+) mm\^3 commanded")
_SATURATED = re.compile(r"SMF's correction saturated at the valve's \[[^]]*\] mm\^3/s .*"
                        r"delivers ([-+0-9.eE]+) of ([-+0-9.eE]+) mm\^3 commanded")


def _volumes(findings: Sequence[tuple[int, str]], kind: re.Pattern
             ) -> tuple[int, int, float, float]:
    """(paths, layers, delivered mm^3, commanded mm^3) of the findings ``kind`` matches,
    whose groups are the delivered and commanded volumes."""
    paths, layers, got, asked = 0, set(), 0.0, 0.0
    for layer, text in findings:
        m = kind.search(text)
        if m:
            paths += 1
            layers.add(int(layer))
            got += float(m.group(1))
            asked += float(m.group(2))
    return paths, len(layers), got, asked


def clamped_volume(findings: Sequence[tuple[int, str]]) -> tuple[int, int, float, float]:
    """What ``flow.out_of_range = "clamp"`` clamped, from valve findings (``(layer,
    text)`` pairs of ``icefab.flow``): (paths, layers, delivered mm^3, commanded mm^3) of
    the paths whose flow or frequency was clamped."""
    return _volumes(findings, _CLAMPED)


def saturated_volume(findings: Sequence[tuple[int, str]]) -> tuple[int, int, float, float]:
    """Where the valve saturated SMF's correction (thesis 5.2.2, ``icefab.flow.
    valve_frequency``), from valve findings (``(layer, text)`` pairs): (paths, layers,
    delivered mm^3, asked mm^3) of those paths."""
    return _volumes(findings, _SATURATED)


def warnings_text(warnings: Sequence[str], source: str = "") -> str:
    """The full list as the text of ``COMMAND-warnings.txt``: a heading line, then one warning a
    line (newlines inside a warning replaced by spaces)."""
    head = f"# {len(warnings)} warnings" + (f" of {source}" if source else "")
    return "\n".join([head, *(w.replace("\n", " ") for w in warnings)]) + "\n"
