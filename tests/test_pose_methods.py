"""A pose method is one class and one registry line (docs/pose_methods.md); the measurement
reads features -> method.estimate -> method.budget -> verdict without knowing any method."""

from __future__ import annotations

import ast
import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

import cutterpose
from cutterpose import methods
from cutterpose.cli import app
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from cutterpose.solvers.estimate import PoseEstimate
from cutterpose.solvers.method import CorrespondenceMethod
from test_features import SCALE, small_camera

TRUE = Pose.from_euler(1, 2, -3, 4, -5, 605)


class Toy(CorrespondenceMethod):
    """OpenCV's iterative PnP on the corners: the corners' budget and checks come with the
    family."""

    name = "toy"
    description = "OpenCV solvePnP (iterative), a toy"

    def solve(self, points_px, camera, model) -> PoseEstimate:
        P = np.asarray(getattr(model, "points_holder_mm", model), float)
        x = camera.undistort_px(np.asarray(points_px, float))   # ideal pixels of K
        ok, rvec, tvec = cv2.solvePnP(P, x, camera.K, np.zeros(5),
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return PoseEstimate.failure(self.name, "solvePnP found nothing")
        return PoseEstimate(self.name, cv2.Rodrigues(rvec)[0], tvec.ravel())


@pytest.fixture
def toy_registered(monkeypatch):
    monkeypatch.setitem(methods.REGISTRY, "toy", "test_pose_methods:Toy")


def test_a_toy_method_measures_through_the_cli(tmp_path, toy_registered):
    """One class and one registry line: ``cutterpose measure --method toy`` measures with it,
    judged by its family's budget (fails if the CLI or the pipeline needed anything else)."""
    cam = small_camera()
    save_camera(cam, tmp_path / "cam.json")
    img = render_holder(TRUE, cam, default_holder(), "easy", seed=2).image
    cv2.imwrite(str(tmp_path / "good.png"), img)
    res = CliRunner().invoke(app, ["measure", str(tmp_path / "good.png"), "--camera",
                                   str(tmp_path / "cam.json"), "--method", "toy", "--json",
                                   "--edge-break-mm", "0", "--budget-tol-mm", str(1.0 / SCALE),
                                   "--budget-tol-deg", str(0.3 / SCALE)])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert d["method"] == "toy" and d["quality"]["ok"], d["quality"]["reason"]
    dof = np.array([d["pose"][k] for k in ("alpha_deg", "beta_deg", "gamma_deg", "X_mm",
                                            "Y_mm", "Z_mm")])
    err = np.abs(dof - TRUE.dof)
    assert np.all(err[:3] < 0.2 / SCALE) and np.all(err[3:] < 0.5 / SCALE), err
    assert set(d["quality"]["budget"]["parts"]) >= {"noise", "method"}
    listed = CliRunner().invoke(app, ["methods"])
    assert "toy" in listed.stdout and "a toy" in listed.stdout


def test_registry_resolves_classes_lazily_and_objects_travel():
    """Every registered name gives an instance of its class with that name; ``+lm`` wraps a
    correspondence method and pickles (worker processes); a range search refuses ``+lm``."""
    for name in methods.available_methods():
        m = methods.get_method(name)
        assert m.name == name and m.description
    lm = methods.get_method("epnp+lm")
    assert lm.name == "epnp+lm" and pickle.loads(pickle.dumps(lm)).name == "epnp+lm"
    with pytest.raises(cutterpose.errors.InputError):
        methods.get_method("dm+lm")
    with pytest.raises(cutterpose.errors.InputError):
        methods.get_method("nope")


def test_what_the_tracker_asks_is_on_the_method():
    """The tracker asks the method, not its name: whether its pose is the design edge's and
    whether it measures again from a tracked pose."""
    b, r, p = (methods.get_method(n) for n in ("dm+b", "dm+r", "dm+"))
    assert b.refines_design_edge and r.refines_design_edge and not p.refines_design_edge
    assert b.reanchors and not r.reanchors and not p.reanchors
    assert not b.needs_corners and r.needs_corners and p.needs_corners


def _names_in(tree) -> set:
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}


def test_the_pipeline_and_the_tracker_know_no_method():
    """``pipeline.py`` and the tracker compare no string with a method's name and read no
    ``info``: they ask the method object (fails on ``method == "dm+b"`` or ``est.info[...]``)."""
    pkg = Path(cutterpose.__file__).parent
    names = set(methods.REGISTRY)
    for path in [pkg / "pipeline.py", *sorted((pkg / "tracking").glob("*.py"))]:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Compare):
                consts = [c.value for c in [node.left, *node.comparators]
                          if isinstance(c, ast.Constant)]
                assert not names & set(consts), (path.name, ast.unparse(node))
        assert "info" not in _names_in(tree), path.name
