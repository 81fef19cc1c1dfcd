"""``pipeline.person_px`` on rendered views: the shrunk frame still shows the model every walker,
and no longer shows it the photos' grain as people (``python -m sim.evidence.lens_recall`` and
``python -m sim.evidence.false_positives``, both with ``--person-px``)."""

from __future__ import annotations

from sim.evidence.false_positives import lawn_false_positives
from sim.evidence.false_positives import main as false_positives_main
from sim.evidence.lens_recall import recall_by_angle


def test_every_walker_found_on_the_full_frame_is_found_on_the_shrunk_one() -> None:
    """Drawn ground, a pinhole from 5 and 8 m (shrunk to 0.25 and 0.34 of the frame): people are
    30-55 px across there, 12 px and more once shrunk, where the model is validated."""
    full = recall_by_angle("pinhole:70", [5.0, 8.0], [1, 2, 3, 4], frames=3, walkers=150)
    shrunk = recall_by_angle("pinhole:70", [5.0, 8.0], [1, 2, 3, 4], frames=3, walkers=150, person_px=12.0)
    assert shrunk["person_px"] == 12.0 and full["person_px"] == 0.0
    people = sum(b["people"] for b in full["bins"])
    assert people >= 15 and people == sum(b["people"] for b in shrunk["bins"])
    assert sum(b["found"] for b in full["bins"]) == people
    assert sum(b["found"] for b in shrunk["bins"]) == people


def test_the_photos_paving_is_no_longer_taken_for_people(photos: str, model_path) -> None:
    """Photo seed 13 (a free circle on the paving of photo 326, nobody in it) from 8 m: the full
    frame marks a fifth of the circle (asphalt grain), the frame shrunk to 12 px a person marks
    almost none of it."""
    from companion.pipeline.density import DensityModel

    model = DensityModel(model_path, threads=2)
    (full,) = lawn_false_positives(model, 13, [8.0], photos)
    (shrunk,) = lawn_false_positives(model, 13, [8.0], photos, person_px=12.0)
    assert full.ground == "photo" and full.circle_pct > 10.0
    assert shrunk.circle_pct < 1.0


def test_a_bad_person_px_is_exit_2(capsys) -> None:
    assert false_positives_main(["--seeds", "1", "--person-px", "-3"]) == 2
    assert "--person-px" in capsys.readouterr().err
