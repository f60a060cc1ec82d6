"""Action recognition experiment (Table 3.3) on BasicMotions, smoke sizes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("aeon")

from hgpdm_torch.experiments.action_recognition import action_recognition, load_actions  # noqa: E402


def test_loader_subsamples_the_real_data():
    z_train, y_train, z_test, y_test, names = load_actions(subsample=3)
    assert z_train.shape == (40, 34, 6) and z_test.shape == (40, 34, 6)
    assert names == sorted(names) and len(names) == 4
    assert sorted(y_train.unique().tolist()) == [0, 1, 2, 3]


def test_table_is_consistent_with_its_confusion_matrices():
    table = action_recognition(
        fit_steps=5, windows=(4,), forgettings=(0.2,), max_train=2, max_test=1, subsample=5
    )
    methods = table.column("method")
    assert methods[:2] == ["IDDM batch n=4", "IDDM online eps=0.2"]
    assert {"SVM n=5", "GPC n=5"} <= set(methods)
    decisions = table.meta["n_test"] * table.meta["frames"]
    for row in table.rows:
        m = np.asarray(table.meta["confusion"][row["method"]])
        assert m.shape == (4, 4) and m.sum() == decisions
        assert abs(100 * np.trace(m) / decisions - row["accuracy [%]"]) < 0.06
        assert row["CPU ms/decision"] > 0
