"""NC text of scripts/make_samples.py: a Fanuc/ISO block writer and the programs' header and footer."""
from __future__ import annotations

SAFE_Z = 25.0   # clearance plane of every sample program, mm above the parting face


class NCWriter:
    """Fanuc/ISO-style block writer: N numbers, modal G/F and coordinates, 3 decimals."""

    def __init__(self, n_step: int = 2):
        self.lines: list[str] = []
        self.n = 0
        self.n_step = n_step
        self.pos = {"X": None, "Y": None, "Z": None}
        self.motion = None
        self.feed = None
        self.moves = {"G0": 0, "G1": 0, "G2": 0, "G3": 0}

    @staticmethod
    def num(v: float) -> str:
        s = f"{v:.3f}"
        return "0.000" if s == "-0.000" else s

    def raw(self, text: str) -> None:
        self.lines.append(text)

    def block(self, text: str) -> None:
        self.n += self.n_step
        self.lines.append(f"N{self.n} {text}")

    def _coords(self, words: list, x, y, z) -> bool:
        """Append the coordinates that change (modal); whether any did."""
        changed = False
        for ax, v in (("X", x), ("Y", y), ("Z", z)):
            if v is None:
                continue
            s = self.num(v)
            if s != self.pos[ax]:
                words.append(ax + s)
                self.pos[ax] = s
                changed = True
        return changed

    def _emit(self, g: str, words: list, feed) -> None:
        if feed is not None and feed != self.feed:
            words.append(f"F{feed:g}")
            self.feed = feed
        self.motion = g
        self.block(" ".join(words))
        self.moves[g] += 1

    def move(self, g: str, x=None, y=None, z=None, feed=None, extra: str = "", force=False):
        words = [g] if g != self.motion or force else []
        changed = self._coords(words, x, y, z)
        if extra:
            words.append(extra)
            changed = True
        if not changed:
            return False
        self._emit(g, words, None if g == "G0" else feed)
        return True

    def arc(self, g: str, x, y, z=None, i=None, j=None, k=None, r=None, feed=None, plane=""):
        """Circular move; I J K incremental centre or R. ``plane`` prefixes e.g. 'G18'."""
        words = ([plane] if plane else []) + [g]
        self._coords(words, x, y, z)
        for ax, v in (("I", i), ("J", j), ("K", k), ("R", r)):
            if v is not None:
                words.append(ax + self.num(v))
        self._emit(g, words, feed)

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


def header(w: NCWriter, number: int, title: str, comments: list[str], tool: int = 1,
           spindle_rpm: int = 12000) -> None:
    """Program start: ``%``, O number and title, comments, modal reset, tool change, spindle on."""
    w.raw("%")
    w.raw(f"O{number} ({title})")
    for c in comments:
        w.raw(f"({c})")
    w.block("G90 G17 G21 G40 G49 G80")
    w.block(f"T{tool} M6")
    w.block(f"S{spindle_rpm} M3")


def footer(w: NCWriter) -> None:
    """Program end: retract to the clearance plane, spindle off, M30, ``%``."""
    w.move("G0", z=SAFE_Z)
    w.block("M5")
    w.block("M30")
    w.raw("%")
