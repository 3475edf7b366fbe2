"""`--state DIR` keeps the detector settings the map was built with; a run that continues the map
with other settings says which, in one warning line."""

from __future__ import annotations

import logging

from aefabmap.cli.state_options import open_state
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id
from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence
from tests.conftest import make_synthetic_bundle


def test_a_state_built_with_other_settings_loads_with_a_warning_naming_them(tmp_path, caplog):
    bundle = make_synthetic_bundle(tmp_path / "bundle", vocabulary_size=64)
    built = load_detector(bundle, DetectorConfig(exclude=2))
    images, _ = generate_loop_sequence(8, seed=1, size=(160, 120))
    for i, img in enumerate(images):
        built.process(img, i)
    with MapStateDir(tmp_path / "state", bundle_id(built.manifest)) as d:
        d.save(built.state())
    log = logging.getLogger("test.state")

    same = load_detector(bundle, DetectorConfig(exclude=2))
    with caplog.at_level(logging.INFO, logger="test.state"):
        open_state(tmp_path / "state", same, log).close()
    assert same.n_places == built.n_places and "other detector settings" not in caplog.text

    caplog.clear()
    other = load_detector(bundle, DetectorConfig(exclude=3, candidates=CandidateConfig(top_k=2)))
    with caplog.at_level(logging.INFO, logger="test.state"):
        open_state(tmp_path / "state", other, log).close()
    assert other.n_places == built.n_places
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "candidates.top_k" in warning[0] and "exclude" in warning[0]
