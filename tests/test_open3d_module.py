"""open3d imported without its plotly drawing (``fullview.sfm.open3d_module``): the same open3d, 600 fewer modules."""

import subprocess
import sys

_SCRIPT = """
import sys
import numpy as np
from fullview.sfm.open3d_module import open3d
o3d = open3d()
loaded = sorted(m for m in ("plotly", "dash", "IPython", "werkzeug") if m in sys.modules)
# open3d itself works: normals of a plane's points
rng = np.random.default_rng(0)
pts = np.column_stack([rng.uniform(0, 1, (500, 2)), np.zeros(500)])
pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
assert np.allclose(np.abs(np.asarray(pcd.normals)[:, 2]), 1.0)
try:
    o3d.visualization.draw_plotly([pcd])
    said = "no error"
except RuntimeError as e:
    said = str(e)
print(loaded, "|", said)
"""


def _run(script: str) -> str:
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout.strip()


def test_open3d_without_plotly_drawing():
    loaded, said = _run(_SCRIPT).split(" | ")
    assert loaded == "[]"  # a plain `import open3d` loads all four
    assert "plotly drawing is not loaded" in said and "draw_plotly" in said


def test_open3d_imported_before_is_left_alone():
    out = _run("import open3d, sys\nfrom fullview.sfm.open3d_module import open3d as get\n"
               "assert get() is open3d\nprint('plotly' in sys.modules, callable(open3d.visualization.draw_plotly))")
    assert out == "True True"
