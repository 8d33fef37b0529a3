"""Installation mistakes between the machine and the DAQ, for `millsense commission`'s tests.

What an electrician can get wrong while every sensor is sound, written from the
wiring's side, knowing nothing of how the daemon judges it:

- `swap` (A, B): two channels' cables on each other's inputs (two phases out of
  order, `--swap i_v,i_w`);
- `reverse` A: a sensor turned round (a hall sensor mounted the wrong way: its
  counts negated) or, for the encoder, A and B swapped (it counts backwards).

Everything else (feed hold, truth, history, duration) is the wrapped source's.
"""

from __future__ import annotations

import numpy as np


class WiringFaults:
    """Any sample source, with channels swapped or turned round."""

    def __init__(self, source, *, swap: list[tuple[str, str]] | None = None, reverse: list[str] | None = None) -> None:
        object.__setattr__(self, "_source", source)
        names = list(source.descriptor.names)
        cols = []
        for a, b in swap or ():
            for name in (a, b):
                if name not in names:
                    raise ValueError(f"cannot swap {name}: the DAQ sends {', '.join(names)}")
            if a == b:
                raise ValueError(f"cannot swap {a} with itself")
            cols.append((names.index(a), names.index(b)))
        unknown = [n for n in reverse or () if n not in names]
        if unknown:
            raise ValueError(f"cannot reverse {', '.join(unknown)}: the DAQ sends {', '.join(names)}")
        object.__setattr__(self, "_swap", cols)
        object.__setattr__(self, "_reverse", [names.index(n) for n in reverse or ()])

    def step(self, n: int) -> np.ndarray:
        counts = np.array(self._source.step(n), dtype=np.int16)
        for a, b in self._swap:
            counts[:, [a, b]] = counts[:, [b, a]]
        for col in self._reverse:
            # two's complement negation: -32768 stays, as a 16-bit counter running backwards wraps
            counts[:, col] = (-counts[:, col].astype(np.int32)).astype(np.int16)
        return counts

    def __getattr__(self, name):
        return getattr(self._source, name)

    def __setattr__(self, name, value):
        setattr(self._source, name, value)   # feed_hold from the device goes to the machine
