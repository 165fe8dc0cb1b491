"""Text to 6- and 8-dot Braille (Unicode Braille patterns), and cells laid out on a pin grid.

Unicode's Braille block encodes a cell as ``U+2800 + sum(2**(d - 1) for d in dots)`` (dots 1-3
and 7 down the left column, 4-6 and 8 down the right). Text becomes patterns by one of:

* ``dots=6``: English uncontracted (grade 1) literary Braille: letters, the capital sign
  (dot 6) before a capital, the number sign (dots 3456) before a run of digits (digits are the
  letters a-j; a letter a-j right after digits gets the letter sign, dots 56), and the common
  punctuation ``, ; : . ! ? ' -``.
* ``dots=8``: North American computer Braille (NABCC), one cell per ASCII character: the 6-dot
  Braille ASCII table for codes 32-95, dot 7 added for 64-95 (capitals and ``@[\\]^_``), and
  codes 96-126 as 64-94 without dot 7 (lower case).

Characters already in the Braille block pass through unchanged (6-dot mode refuses those using
dots 7 or 8).
"""

from __future__ import annotations

import numpy as np

from rtctl.errors import SceneError

__all__ = ["to_unicode", "cell_dots", "braille_frames", "BRAILLE_ASCII"]

#: Braille ASCII (the 6-dot part of NABCC): character for the cell with bit pattern ``i``
#: (bit ``d - 1`` set for dot ``d``), ``i = 0..63``.
BRAILLE_ASCII = " A1B'K2L@CIF/MSP\"E3H9O6R^DJG>NTQ,*5<-U8V.%[$+X!&;:4\\0Z7(_?W]#Y)="
_ASCII6 = {ch: i for i, ch in enumerate(BRAILLE_ASCII)}
_BASE = 0x2800
_DOT7 = 1 << 6
_CAPITAL, _NUMBER, _LETTER = 0b100000, 0b111100, 0b110000       # dot 6; 3456; 56
_PUNCT6 = {",": 0b10, ";": 0b110, ":": 0b10010, ".": 0b110010, "!": 0b10110, "?": 0b100110, "'": 0b100,
           "-": 0b100100, " ": 0}


def _letter(ch):
    return _ASCII6[ch.upper()]


def _six(text):
    cells, in_number = [], False
    for ch in text:
        o = ord(ch)
        if _BASE <= o <= _BASE + 0xFF:
            if o - _BASE > 63:
                raise SceneError(f"{ch!r} uses dots 7/8; 6-dot Braille cannot show it (use dots=8)")
            cells.append(o - _BASE)
            in_number = False
        elif ch.isascii() and ch.isdigit():
            if not in_number:
                cells.append(_NUMBER)
                in_number = True
            cells.append(_letter("j" if ch == "0" else chr(ord("a") + int(ch) - 1)))
        elif ch.isascii() and ch.isalpha():
            if in_number and ch.lower() in "abcdefghij":
                cells.append(_LETTER)
            if ch.isupper():
                cells.append(_CAPITAL)
            cells.append(_letter(ch))
            in_number = False
        elif ch in _PUNCT6:
            cells.append(_PUNCT6[ch])
            in_number = in_number and ch in ",."  # 1,000 and 3.14 stay one number
        else:
            raise SceneError(f"character {ch!r} has no 6-dot Braille here; use dots=8 (ASCII) or Unicode Braille")
    return cells


def _eight(text):
    cells = []
    for ch in text:
        o = ord(ch)
        if _BASE <= o <= _BASE + 0xFF:
            cells.append(o - _BASE)
        elif 32 <= o <= 63:
            cells.append(_ASCII6[ch])
        elif 64 <= o <= 95:
            cells.append(_ASCII6[ch] | _DOT7)
        elif 96 <= o <= 126:
            cells.append(_ASCII6[chr(o - 32)])
        else:
            raise SceneError(f"character {ch!r} is not ASCII; 8-dot computer Braille covers ASCII 32-126")
    return cells


def to_unicode(text: str, dots: int = 6) -> str:
    """Text as a string of Unicode Braille patterns (U+2800-U+28FF).

    Parameters
    ----------
    text : str
    dots : {6, 8}
        Literary 6-dot (with capital and number signs) or 8-dot computer Braille.

    Examples
    --------
    >>> to_unicode("hello world")
    '⠓⠑⠇⠇⠕⠀⠺⠕⠗⠇⠙'
    >>> to_unicode("Dot 4", dots=8)
    '⡙⠕⠞⠀⠲'
    """
    if dots not in (6, 8):
        raise SceneError(f"dots = {dots!r}; Braille cells have 6 or 8 dots")
    cells = _six(text) if dots == 6 else _eight(text)
    return "".join(chr(_BASE + c) for c in cells)


def cell_dots(ch: str, dots: int = 8) -> np.ndarray:
    """Pins of one Braille pattern: bool ``(4, 2)`` for 8 dots, ``(3, 2)`` for 6 (True = up).

    Examples
    --------
    >>> cell_dots("⠙", dots=6).astype(int)       # d = dots 1, 4, 5
    array([[1, 1],
           [0, 1],
           [0, 0]])
    """
    v = ord(ch) - _BASE
    if not 0 <= v <= 0xFF:
        raise SceneError(f"{ch!r} is not a Unicode Braille pattern (U+2800-U+28FF)")
    order = ((1, 4), (2, 5), (3, 6), (7, 8))[: 4 if dots == 8 else 3]
    return np.array([[bool(v >> (d - 1) & 1) for d in row] for row in order])


def braille_frames(text: str, grid=(4, 4), dots: int = 8, gap: int = 0) -> np.ndarray:
    """Lay the Braille cells of ``text`` onto a pin grid, page by page.

    Cells (``4 x 2`` or ``3 x 2`` pins) fill the grid left to right, then top to bottom, with
    ``gap`` empty pins between neighbouring cells (0 for the Dot display, whose 4x4 matrix is
    two 2x4 Braille cells side by side); text that does not fit continues on the next frame.

    Parameters
    ----------
    text : str
    grid : (int, int)
        Pins (rows, cols).
    dots : {6, 8}
    gap : int
        Empty pins between cells, horizontally and vertically.

    Returns
    -------
    ndarray, bool, shape (n_frames, rows, cols)

    Examples
    --------
    >>> braille_frames("ab", grid=(4, 4))[0].astype(int)
    array([[1, 0, 1, 0],
           [0, 0, 1, 0],
           [0, 0, 0, 0],
           [0, 0, 0, 0]])
    """
    R, C = (int(v) for v in grid)
    cr = 4 if dots == 8 else 3
    per_row = (C + gap) // (2 + gap)
    per_col = (R + gap) // (cr + gap)
    if per_row < 1 or per_col < 1:
        raise SceneError(f"a {cr}x2 Braille cell does not fit the {R}x{C} grid")
    chars = to_unicode(text, dots)
    per = per_row * per_col
    n = max(1, -(-len(chars) // per))
    frames = np.zeros((n, R, C), dtype=bool)
    for k, ch in enumerate(chars):
        f, q = divmod(k, per)
        i, j = divmod(q, per_row)
        r0, c0 = i * (cr + gap), j * (2 + gap)
        frames[f, r0:r0 + cr, c0:c0 + 2] = cell_dots(ch, dots)
    return frames
