"""`tesseract4d research phrasings` (evaluation/still_phrasings.py): every keep-still phrasing asked in every
held-out scene."""

from __future__ import annotations

import json

import numpy as np
from tesseract4d.testing.synthetic_scene import write_grouped_dataset


def test_every_phrasing_in_every_scene_against_the_scene_s_true_motion(micro_checkpoint, tmp_path, capsys):
    from tesseract4d import dataset_format as df
    from tesseract4d.evaluation.heldout_believability import clip_motion

    from tesseract4d.cli import main

    data = write_grouped_dataset(tmp_path / "groups", scenes=2)
    out = tmp_path / "probe.json"
    assert main(["research", "phrasings", "--heldout", str(data), "--checkpoint", str(micro_checkpoint),
                 "--sample-seed", "0", "1", "--phrase", "stay still", "don't move", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| stay still | given |" in printed and "| don't move | given |" in printed

    report = json.loads(out.read_text())[str(micro_checkpoint)]
    assert set(report) == {"stay still", "don't move"}
    # The limit of scene 0: a tenth of its two true (active) futures' mean motion.
    truth = [df.read_episode(p) for p in sorted((data / "episodes").glob("*/seed_000000*.h5"))]
    assert len(truth) == 2
    limit0 = 0.1 * np.mean([clip_motion(np.asarray(next(iter(ep.cameras.values())).rgb)) for ep in truth])
    for entry in report.values():
        assert entry["clips"] == 4 and len(entry["motion"]) == 4  # 2 scenes x 2 noise seeds
        assert entry["limit"][0] == entry["limit"][2] == np.float64(limit0) > 0
        assert entry["still"] == sum(m <= lim for m, lim in zip(entry["motion"], entry["limit"]))
        assert all(np.isfinite(entry["motion"]))
    # The second noise seed draws other clips.
    assert report["stay still"]["motion"][:2] != report["stay still"]["motion"][2:]


def test_default_phrasings_are_the_skill_library_s_and_bad_input_is_one_line(tmp_path, capsys):
    from tesseract4d.cli import main
    from tesseract4d.evaluation.still_phrasings import keep_still_phrasings

    phrasings = keep_still_phrasings()
    assert ("don't move", "heldout") in phrasings and ("stay still", "train") in phrasings

    assert main(["research", "phrasings", "--heldout", str(tmp_path / "nothing")]) == 2
    assert "not a dataset folder" in capsys.readouterr().err
    taken = tmp_path / "taken.json"
    taken.write_text("{}")
    assert main(["research", "phrasings", "--heldout", str(tmp_path), "--json", str(taken)]) == 2
    assert "exists" in capsys.readouterr().err
    assert taken.read_text() == "{}"
