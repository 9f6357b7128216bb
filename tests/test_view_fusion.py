"""benchmarks/view_fusion.py: the views' shared error and the fusion table on records whose
errors are drawn with a known correlation."""

import importlib.util
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

_path = Path(__file__).resolve().parents[1] / "benchmarks" / "view_fusion.py"
_spec = importlib.util.spec_from_file_location("view_fusion", _path)
vf = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(vf)


def _records(rng, holders, views, rho, sd):
    """Records as view_errors.py writes them: camera-frame poses whose holder-frame errors
    share ``rho`` of their variance between the views of a holder; the covariance given is the
    errors' own (own axes for the rotation, camera axes for the translation)."""
    out = []
    for h in range(holders):
        shared = rng.normal(size=6)
        for v in range(views):
            e = sd * (np.sqrt(rho) * shared + np.sqrt(1 - rho) * rng.normal(size=6))
            R_t = Rotation.from_euler("xyz", rng.uniform(-8, 8, 3), degrees=True).as_matrix()
            t_t = np.array([*rng.uniform(-15, 15, 2), rng.uniform(580, 650)])
            # holder-frame error (dt, dphi): T_est = T_true (Exp(dphi), dt)
            R_e = R_t @ Rotation.from_rotvec(e[3:]).as_matrix()
            t_e = t_t + R_t @ e[:3]
            C_h = np.diag(sd ** 2)
            J = np.eye(6)
            J[:3, :3] = R_t            # translation to the camera's axes, rotation own axes
            out.append({"file": f"{h}_{v}.png", "holder_index": h, "view": v,
                        "accepted": True, "reason": "", "R_est": R_e.tolist(),
                        "t_est_mm": t_e.tolist(), "R_true": R_t.tolist(),
                        "t_true_mm": t_t.tolist(), "covariance_cam": (J @ C_h @ J.T).tolist()})
    return out


def test_icc_of_known_groups():
    rng = np.random.default_rng(0)
    groups = []
    for _ in range(4000):
        s = rng.normal(size=2)
        groups.append(np.stack([np.sqrt(0.6) * s + np.sqrt(0.4) * rng.normal(size=2)
                                for _ in range(3)]))
    assert np.allclose(vf.icc(groups), 0.6, atol=0.03)


def test_view_fusion_reports_the_shared_error_and_covers_when_told_it(tmp_path, capsys):
    rng = np.random.default_rng(1)
    sd = np.array([0.05, 0.05, 0.2, 1e-3, 1e-3, 1e-4])
    doc = {"set": "synthetic", "method": "dm+b", "edge_look": None,
           "images": _records(rng, 300, 3, 0.4, sd)}
    path = tmp_path / "views.json"
    path.write_text(json.dumps(doc))
    vf.main([str(path), "--rho", "0.4"])
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("whitened errors"))
    same = float(line.split("E[z_i.z_i]/6 = ")[1].split()[0])
    ratio = float(line.rsplit(" ", 1)[1])
    assert abs(same - 1.0) < 0.1 and abs(ratio - 0.4) < 0.08, line
    # fused under the right correlation, the 3-sigma figures cover nearly every holder
    rows = [ln for ln in out.splitlines() if ln.startswith("| 3 |")]
    covered, n = (int(x) for x in rows[-1].split("|")[7].split(" of "))
    assert covered >= 0.9 * n, rows[-1]
