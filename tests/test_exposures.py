"""Known exposure values: both file forms, and clear errors naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.exposures import load_exposures

NAMES = ["images/a.png", "images/b.png"]


def test_mapping_and_camera_truth_forms(tmp_path):
    mapping = tmp_path / "ev.json"
    mapping.write_text(json.dumps({"b": 2, "a.jpg": -1.5}))
    assert np.allclose(load_exposures(mapping, NAMES), [-1.5, 2.0])
    truth = tmp_path / "camera_truth.json"
    truth.write_text(
        json.dumps({"views": [{"file": "images/a.png", "ev": 3.0}, {"file": "images/b.png", "ev": 0}]})
    )
    assert np.allclose(load_exposures(truth, NAMES), [3.0, 0.0])


@pytest.mark.parametrize(
    "content, message",
    [
        ("{", "not valid JSON"),
        ("[1, 2]", "expected a JSON object"),
        ('{"a": 1}', "no exposure for 1 of the scene's 2 images: b"),
        ('{"a": 1, "b": "bright"}', "not a finite number"),
        ('{"a": 1, "b": NaN}', "not a finite number"),
        ('{"views": [{"file": "a.png"}]}', "needs 'file' and 'ev'"),
    ],
)
def test_bad_exposure_files(tmp_path, content, message):
    path = tmp_path / "ev.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as e:
        load_exposures(path, NAMES)
    assert str(path) in str(e.value)
