"""A small Hangul stroke font: jamo drawn as polylines and composed into syllable blocks."""

from __future__ import annotations

import math

import numpy as np

from sgf_plugins.world.canvas import Point

_JAMO: dict[str, list[list[Point]]] = {
    "ㄱ": [[(0.12, 0.15), (0.85, 0.15), (0.85, 0.9)]],
    "ㄴ": [[(0.15, 0.1), (0.15, 0.85), (0.9, 0.85)]],
    "ㄷ": [[(0.85, 0.15), (0.15, 0.15), (0.15, 0.85), (0.9, 0.85)]],
    "ㄹ": [[(0.12, 0.12), (0.85, 0.12), (0.85, 0.48), (0.15, 0.48), (0.15, 0.86), (0.9, 0.86)]],
    "ㅁ": [[(0.15, 0.15), (0.85, 0.15), (0.85, 0.85), (0.15, 0.85), (0.15, 0.15)]],
    "ㅂ": [[(0.15, 0.08), (0.15, 0.88), (0.85, 0.88), (0.85, 0.08)], [(0.15, 0.48), (0.85, 0.48)]],
    "ㅅ": [[(0.5, 0.1), (0.45, 0.42), (0.1, 0.9)], [(0.47, 0.45), (0.9, 0.9)]],
    "ㅇ": [[(0.5 + 0.36 * math.cos(a), 0.5 + 0.36 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 25)]],
    "ㅈ": [[(0.12, 0.15), (0.88, 0.15)], [(0.5, 0.15), (0.1, 0.9)], [(0.5, 0.45), (0.9, 0.9)]],
    "ㅊ": [
        [(0.42, 0.0), (0.6, 0.1)],
        [(0.12, 0.26), (0.88, 0.26)],
        [(0.5, 0.26), (0.1, 0.95)],
        [(0.5, 0.52), (0.9, 0.95)],
    ],
    "ㅎ": [
        [(0.36, 0.04), (0.64, 0.04)],
        [(0.12, 0.22), (0.88, 0.22)],
        [(0.5 + 0.24 * math.cos(a), 0.64 + 0.24 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 21)],
    ],
    "ㅏ": [[(0.4, 0.0), (0.4, 1.0)], [(0.4, 0.48), (0.85, 0.48)]],
    "ㅓ": [[(0.6, 0.0), (0.6, 1.0)], [(0.15, 0.48), (0.6, 0.48)]],
    "ㅣ": [[(0.5, 0.0), (0.5, 1.0)]],
    "ㅐ": [[(0.3, 0.0), (0.3, 1.0)], [(0.3, 0.48), (0.62, 0.48)], [(0.75, 0.0), (0.75, 1.0)]],
    "ㅗ": [[(0.5, 0.25), (0.5, 0.68)], [(0.0, 0.68), (1.0, 0.68)]],
    "ㅜ": [[(0.0, 0.3), (1.0, 0.3)], [(0.5, 0.3), (0.5, 0.78)]],
    "ㅡ": [[(0.0, 0.5), (1.0, 0.5)]],
}
_INITIALS = "ㄱㄲㄴㄷㄸㄹㅁㅂㅃㅅㅆㅇㅈㅉㅊㅋㅌㅍㅎ"
_MEDIALS = "ㅏㅐㅑㅒㅓㅔㅕㅖㅗㅘㅙㅚㅛㅜㅝㅞㅟㅠㅡㅢㅣ"
_FINALS = " ㄱㄲㄳㄴㄵㄶㄷㄹㄺㄻㄼㄽㄾㄿㅀㅁㅂㅄㅅㅆㅇㅈㅊㅋㅌㅍㅎ"
_HORIZONTAL_VOWELS = "ㅗㅜㅡ"


def hangul_strokes(word: str) -> list[list[Point]]:
    """Strokes of a Hangul word in a unit box per syllable laid side by side (u in [0, n])."""
    out: list[list[Point]] = []
    for i, ch in enumerate(word):
        code = ord(ch) - 0xAC00
        if not 0 <= code < 11172:
            raise ValueError(f"{ch!r} is not a Hangul syllable")
        initial, medial, final = _INITIALS[code // 588], _MEDIALS[(code % 588) // 28], _FINALS[code % 28].strip()
        horizontal = medial in _HORIZONTAL_VOWELS
        if horizontal:
            boxes = (
                [(0.2, 0.0, 0.8, 0.35), (0.0, 0.3, 1.0, 0.6), (0.15, 0.62, 0.85, 1.0)]
                if final
                else [
                    (0.15, 0.0, 0.85, 0.5),
                    (0.0, 0.45, 1.0, 0.9),
                ]
            )
        else:
            boxes = (
                [(0.0, 0.0, 0.6, 0.5), (0.55, 0.0, 1.0, 0.6), (0.1, 0.62, 0.9, 1.0)]
                if final
                else [
                    (0.0, 0.1, 0.6, 0.9),
                    (0.55, 0.0, 1.0, 1.0),
                ]
            )
        parts = [initial, medial] + ([final] if final else [])
        for jamo, (u0, v0, u1, v1) in zip(parts, boxes, strict=True):
            if jamo not in _JAMO:
                raise ValueError(f"the stroke font has no jamo {jamo!r} (in {word!r})")
            for stroke in _JAMO[jamo]:
                out.append([(i + 0.08 + 0.84 * (u0 + u * (u1 - u0)), v0 + v * (v1 - v0)) for u, v in stroke])
    return out
