"""ctgs.render.constants mirrors kernels/include/ctgs/constants.h: same names, same values."""

from __future__ import annotations

import os
import re

from ctgs.render import constants

HEADER = os.path.join(os.path.dirname(__file__), "..", "..", "kernels", "include", "ctgs", "constants.h")


def test_python_constants_mirror_the_header():
    text = open(HEADER).read()
    found = re.findall(r"constexpr\s+(?:double|float|int)\s+(\w+)\s*=\s*([^;]+);", text)
    assert len(found) >= 10, found
    values: dict[str, float] = {}
    for name, expr in found:
        values[name] = eval(expr, {}, dict(values))  # noqa: S307 (our own header: literals and earlier names)
        assert getattr(constants, name) == values[name], name
    public = {k for k in vars(constants) if k.isupper()}
    assert public == set(values), public ^ set(values)
