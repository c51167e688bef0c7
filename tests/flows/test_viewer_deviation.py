"""The viewer's deviation ramp (viewer/deviation.js), run in node: blue behind, red in front, saturating at
10 cm, grey where a face has no value."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

RAMP = Path(__file__).resolve().parents[2] / "viewer" / "deviation.js"


def _colours(values: list) -> list:
    if shutil.which("node") is None:
        pytest.fail("node is not installed (apt-get install -y nodejs npm)")
    js = (f"import {{ deviationColour }} from {json.dumps(RAMP.as_uri())};"
          f"console.log(JSON.stringify({json.dumps(values)}.map((d) => deviationColour(d === 'nan' ? NaN : d))));")
    out = subprocess.run(["node", "--input-type=module", "-e", js], capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


def test_deviation_ramp_diverges_saturates_and_greys_the_absent():
    behind2, behind, half, zero, front, front2, nan, none = _colours([-0.2, -0.1, 0.05, 0.0, 0.1, 0.2, "nan", None])
    assert behind == behind2 == [0x21, 0x66, 0xAC] and front == front2 == [0xB2, 0x18, 0x2B]  # saturated at 10 cm
    assert zero == [0xF7, 0xF7, 0xF7]
    assert half[0] > half[2] and half[0] < 0xF7 + 1 and half != front  # halfway to red
    assert nan == none == [0x9A, 0x9A, 0x9A]
