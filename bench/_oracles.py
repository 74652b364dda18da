"""The independent references of the robot benchmarks (Pinocchio, python-fcl, pybullet's robot data),
installed in an environment of their own under bench/.oracles (made on first use, then reused; not
part of the project's dependencies) and run in a subprocess: arrays go in and out as .npz files.

    python = oracle_python()                  # bench/.oracles/bin/python, installing it if needed
    panda = panda_urdf()                      # pybullet_data's franka_panda/panda.urdf
    data = pybullet_data()                    # the folder of pybullet's data (meshes, textures)
    out = run_oracle("pinocchio_fk", urdf=..., q=...)     # a task of bench/_oracle_tasks.py
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
VENV = HERE / ".oracles"
PACKAGES = ["pybullet==3.2.7", "pin==4.1.0", "python-fcl==0.7.0.11", "trimesh>=4"]


def oracle_python():
    """The oracles' interpreter, creating bench/.oracles (Python 3.11, pybullet, Pinocchio, fcl) once."""
    python = VENV / "bin" / "python"
    stamp = VENV / ".installed"
    if stamp.exists() and stamp.read_text() == json.dumps(PACKAGES):
        return python
    print(f"installing the benchmark oracles into {VENV} (once) ...", file=sys.stderr, flush=True)
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", *PACKAGES], check=True)
    stamp.write_text(json.dumps(PACKAGES))
    return python


def run_oracle(task, **inputs):
    """Run `task` of _oracle_tasks.py in the oracles' environment: inputs and outputs are arrays
    (strings go as 0-d arrays)."""
    python = oracle_python()
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **{k: np.asarray(v) for k, v in inputs.items()})
        subprocess.run([str(python), str(HERE / "_oracle_tasks.py"), task, str(src), str(dst)], check=True)
        with np.load(dst) as out:
            return {k: out[k] for k in out.files}


def pybullet_data():
    """The folder of pybullet's data (robots, meshes and their textures), as pybullet ships it."""
    path = subprocess.run(
        [str(oracle_python()), "-c", "import pybullet_data; print(pybullet_data.getDataPath())"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return Path(path)


def panda_urdf():
    """The Franka Panda URDF that pybullet ships (pybullet_data), with its meshes beside it."""
    return pybullet_data() / "franka_panda" / "panda.urdf"
