"""The viewer's pure helpers, run in node: the deviation ramp (viewer/deviation.js: blue behind, red in front, saturating at
10 cm, grey where a face has no value) and the measure (viewer/measure.js: distance, height, horizontal)."""

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


def test_measure_splits_distance_into_height_and_horizontal():
    if shutil.which("node") is None:
        pytest.fail("node is not installed (apt-get install -y nodejs npm)")
    mod = (RAMP.parent / "measure.js").as_uri()
    js = (f"import {{ measureBetween }} from {json.dumps(mod)};"
          "console.log(JSON.stringify([measureBetween([1, 2, 3], [4, 6, 3], [0, 0, 1]),"
          " measureBetween([0, 0, 0], [0, 3, 0], [0, 2, 0]), measureBetween([0, 0, 0], [3, 0, -4], [0, 0, 1])]));")
    out = subprocess.run(["node", "--input-type=module", "-e", js], capture_output=True, text=True, timeout=60, check=True)
    flat, vertical, down = json.loads(out.stdout)
    assert flat == {"distance": 5, "height": 0, "horizontal": 5}
    assert vertical == {"distance": 3, "height": 3, "horizontal": 0}  # up need not be unit length
    assert down["height"] == -4 and down["horizontal"] == pytest.approx(3) and down["distance"] == 5
