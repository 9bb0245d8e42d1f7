"""The outsider's five mutation kinds of issue 26 (tests/fuzz/outsider.py) do what they say, reproducibly."""

from __future__ import annotations

import struct

import pytest

from tests.fuzz.mutate import HUGE, OUTSIDER_OPS, mutant

BASE = bytes(range(256)) * 40  # 10,240 bytes, every byte value at a known place


@pytest.mark.parametrize("op", OUTSIDER_OPS)
def test_same_numbers_same_mutant(op: str) -> None:
    """(seed, index, kind) fixes a mutant: a campaign's finding is rebuilt from its three numbers."""
    assert mutant(BASE, 26, 3, op).data == mutant(BASE, 26, 3, op).data
    assert mutant(BASE, 26, 3, op).recipe["op"] == op


def test_each_kind_damages_as_described() -> None:
    """overwrite8 changes at most 8 bytes at its offset, huge_length writes its value there, truncate cuts,
    zero_run zeroes, splice copies a span of the file."""
    for i in range(50):
        m = mutant(BASE, 26, i, "overwrite8")
        at = m.recipe["at"]
        assert len(m.data) == len(BASE) and m.data[:at] == BASE[:at] and m.data[at + 8:] == BASE[at + 8:]
        assert m.data[at:at + 8].hex() == m.recipe["bytes"]
        m = mutant(BASE, 26, i, "huge_length")
        at, width = m.recipe["at"], m.recipe["width"]
        assert m.recipe["value"] in HUGE
        got = struct.unpack_from("<Q" if width == 8 else "<I", m.data, at)[0]
        assert got == m.recipe["value"] and m.data[:at] == BASE[:at] and m.data[at + width:] == BASE[at + width:]
        m = mutant(BASE, 26, i, "truncate")
        assert m.data == BASE[:m.recipe["at"]]
        m = mutant(BASE, 26, i, "zero_run")
        at, n = m.recipe["at"], m.recipe["length"]
        assert m.data[at:at + n] == bytes(len(BASE[at:at + n])) and m.data[:at] == BASE[:at]
        m = mutant(BASE, 26, i, "splice")
        a, b = m.recipe["from"]
        assert BASE[a:b] in m.data
