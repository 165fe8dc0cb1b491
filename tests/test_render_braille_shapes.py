"""Braille against the published alphabet and Unicode's own names; shapes against exact coverage."""

import unicodedata

import numpy as np
import pytest

from rtctl.errors import SceneError
from rtctl.render.braille import braille_frames, cell_dots, to_unicode
from rtctl.render.shapes import SHAPES, shape

# The Braille alphabet (Louis Braille's first decade a-j, + dot 3 for k-t, + dots 3 6 for u-z
# except w), typed from the standard table, independent of the module's Braille ASCII string.
ALPHABET = {
    "a": "1", "b": "12", "c": "14", "d": "145", "e": "15", "f": "124", "g": "1245", "h": "125", "i": "24",
    "j": "245", "k": "13", "l": "123", "m": "134", "n": "1345", "o": "135", "p": "1234", "q": "12345",
    "r": "1235", "s": "234", "t": "2345", "u": "136", "v": "1236", "w": "2456", "x": "1346", "y": "13456",
    "z": "1356",
}


def dots_of(ch):
    name = unicodedata.name(ch)                      # e.g. 'BRAILLE PATTERN DOTS-145'
    return "" if name == "BRAILLE PATTERN BLANK" else name.split("-")[1]


@pytest.mark.parametrize("dots", [6, 8])
def test_alphabet_against_unicode_names(dots):
    for letter, d in ALPHABET.items():
        assert dots_of(to_unicode(letter, dots)) == d, letter


def test_published_strings():
    assert to_unicode("hello world").replace("\u2800", " ") == "⠓⠑⠇⠇⠕ ⠺⠕⠗⠇⠙"
    assert to_unicode("123") == "⠼⠁⠃⠉"                        # number sign + a b c
    assert to_unicode("1a") == "⠼⠁⠰⠁"                         # letter sign after a number
    assert to_unicode("Hi.") == "⠠⠓⠊⠲"                        # capital sign, full stop dots 256
    assert [dots_of(c) for c in to_unicode("A1", dots=8)] == ["17", "2"]  # NABCC: dot 7 capital, lower-cell digit
    assert to_unicode("⠿⣿", dots=8) == "⠿⣿"                    # Braille passes through
    with pytest.raises(SceneError, match="dots 7/8"):
        to_unicode("⣿", dots=6)
    with pytest.raises(SceneError, match="not ASCII"):
        to_unicode("é", dots=8)


def test_cell_layout_follows_the_dot_numbers():
    for v in range(256):
        ch = chr(0x2800 + v)
        cell = cell_dots(ch, 8)
        expect = np.zeros((4, 2), bool)
        for d in dots_of(ch):
            r, c = {"1": (0, 0), "2": (1, 0), "3": (2, 0), "7": (3, 0), "4": (0, 1), "5": (1, 1), "6": (2, 1),
                    "8": (3, 1)}[d]
            expect[r, c] = True
        np.testing.assert_array_equal(cell, expect)


def test_frames_on_the_dot_and_sma_displays():
    f = braille_frames("abc", grid=(4, 4), dots=8)             # Dot: two 2x4 cells per frame
    assert f.shape == (2, 4, 4)
    np.testing.assert_array_equal(f[1, :, :2], cell_dots(to_unicode("c", 8), 8))
    assert not f[1, :, 2:].any()
    g = braille_frames("abcdefgh", grid=(8, 8), dots=6, gap=1)  # SMA 8x8: 3 cells a row, 2 rows
    assert g.shape == (2, 8, 8)
    np.testing.assert_array_equal(g[0, 4:7, 3:5], cell_dots(to_unicode("e"), 6))
    assert not g[0, 3].any() and not g[0, :, 2].any()          # the gaps stay down


def coverage(name, R, C, n=256):
    """Fraction of each pin covered, from an n x n sample grid per pin (exact geometry)."""
    y, x = (np.mgrid[: R * n, : C * n] + 0.5) / n
    if name == "disc":
        inside = (x - C / 2) ** 2 + (y - R / 2) ** 2 <= (min(R, C) / 2) ** 2
    elif name == "ring":
        rad = np.hypot(x - C / 2, y - R / 2)
        inside = np.abs(rad - (min(R, C) / 2 - 0.5)) <= 0.5
    elif name == "triangle":
        inside = np.abs(x - C / 2) <= (C / 2) * (y / R)
    else:  # diagonal band one pin wide
        inside = np.abs(x * R / C - y) * C / np.hypot(R, C) <= 0.5
    return inside.reshape(R, n, C, n).mean(axis=(1, 3))


@pytest.mark.parametrize("name", ["disc", "ring", "triangle", "diagonal"])
@pytest.mark.parametrize("grid", [(4, 4), (8, 8), (6, 8)], ids=["4x4", "8x8", "6x8"])
def test_drawn_shapes_follow_the_half_coverage_rule(name, grid):
    got = shape(name, grid)
    cov = coverage(name, *grid)
    clear = np.abs(cov - 0.5) > 0.06            # rasterization may tip pins right at one half
    np.testing.assert_array_equal(got[clear], cov[clear] > 0.5)


def test_whole_pin_shapes():
    assert shape("square", (4, 4)).all()
    assert shape("frame", (8, 8)).sum() == 28
    assert shape("cross", (5, 5)).sum() == 9 and shape("cross", (8, 8)).sum() == 28
    assert shape("hline", (3, 5)).tolist() == [[False] * 5, [True] * 5, [False] * 5]
    assert set(SHAPES) >= {"square", "disc", "triangle"}
    with pytest.raises(SceneError, match="unknown"):
        shape("star", (4, 4))
