"""The wheel as a user installs it: one top-level name, ``hireps_torch``, and the command
``hireps-train``; the tasks and experiments import from it alone."""

import ast
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel built from the files git would commit (a copy: the build leaves nothing
    in the working tree)."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout")
    tracked = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        )
        .stdout.decode()
        .split("\0")
    )
    src = tmp_path_factory.mktemp("src")
    for name in filter(None, tracked):
        path = ROOT / name
        if not path.is_symlink() and not path.exists():
            continue  # deleted in the working tree, not yet committed
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, src / name, follow_symlinks=False)
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(out),
            str(src),
        ],
        check=True,
        capture_output=True,
    )
    (whl,) = out.glob("*.whl")
    return whl


def test_the_wheel_installs_one_top_level_package_and_the_command(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
        scripts = z.read(entry_points).decode()
    top = {n.split("/")[0] for n in names if ".dist-info/" not in n}
    assert top == {"hireps_torch"}
    for module in ["envs/pendulum.py", "envs/hockey/env.py", "experiments/runner.py", "cli.py"]:
        assert f"hireps_torch/{module}" in names
    assert "hireps-train = hireps_torch.cli:entry" in scripts


# names of ``typing`` newer than Python 3.9, with the version that added them
TYPING_SINCE = {
    **dict.fromkeys(
        ["ParamSpec", "TypeAlias", "TypeGuard", "Concatenate", "is_typeddict"], (3, 10)
    ),
    **dict.fromkeys(["Self", "Unpack", "Never", "LiteralString", "assert_never"], (3, 11)),
    **dict.fromkeys(["NotRequired", "Required", "TypeVarTuple", "reveal_type"], (3, 11)),
    **dict.fromkeys(["override", "TypeAliasType"], (3, 12)),
    **dict.fromkeys(["TypeIs", "ReadOnly", "NoDefault"], (3, 13)),
}


def test_the_wheel_requires_the_python_its_typing_imports_need(wheel):
    with zipfile.ZipFile(wheel) as z:
        (meta,) = [n for n in z.namelist() if n.endswith(".dist-info/METADATA")]
        (line,) = [x for x in z.read(meta).decode().splitlines() if x.startswith("Requires-Python")]
        sources = {n: z.read(n).decode() for n in z.namelist() if n.endswith(".py")}
    least = tuple(int(x) for x in line.split(">=")[1].split("."))
    needed = {}
    for name, text in sources.items():
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module == "typing":
                for alias in node.names:
                    needed[f"{name}: typing.{alias.name}"] = TYPING_SINCE.get(alias.name, (3, 9))
    assert needed, "found no typing import to check"
    too_new = {k: v for k, v in needed.items() if v > least}
    assert not too_new, f"{line} but the wheel imports {too_new}"


def test_the_installed_wheel_imports_the_tasks_and_runs_the_command(wheel, tmp_path):
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    # -S: no site-packages processing, so the editable install of this checkout is not on the
    # path; the dependencies come from this interpreter's site-packages as a plain entry
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), sysconfig.get_paths()["purelib"]]),
    }
    code = (
        "import sys, gymnasium as gym, hireps_torch, hireps_torch.envs, hireps_torch.experiments\n"
        f"assert hireps_torch.__file__.startswith({str(site)!r}), hireps_torch.__file__\n"
        "assert gym.make('hireps/BallOnBeam-v0').reset(seed=0)[0].shape == (3,)\n"
        "for name in ('environments', 'experiments'):\n"
        "    try:\n"
        "        __import__(name)\n"
        "    except ImportError:\n"
        "        pass\n"
        "    else:\n"
        "        raise SystemExit(name + ' is importable')\n"
        "sys.argv = ['hireps-train', '--help']\n"
        "from hireps_torch.cli import entry\n"
        "entry()\n"
    )
    done = subprocess.run(
        [sys.executable, "-S", "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    for experiment in ["bimodal", "pendulum", "ball-on-beam", "hockey-sequential", "sweep"]:
        assert experiment in done.stdout


@pytest.mark.slow
def test_the_wheel_in_a_fresh_virtualenv_imports_each_module_once(wheel, tmp_path):
    """pip install of the wheel into a new virtualenv (its dependencies lent from this one):
    the library, its tasks and its command come from the installed files alone."""
    import venv

    fresh = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(fresh)
    python = fresh / "bin" / "python"
    lent = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    # a plain path entry: the editable install's finder (a .pth of this venv) is not run there
    (Path(lent) / "lent.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(python),
            "install",
            "-q",
            "--no-deps",
            str(wheel),
        ],
        check=True,
        capture_output=True,
    )
    code = (
        "import sys, gymnasium as gym, hireps_torch, hireps_torch.envs, hireps_torch.experiments\n"
        f"assert hireps_torch.__file__.startswith({lent!r}), hireps_torch.__file__\n"
        "assert hireps_torch.envs.__file__.startswith(hireps_torch.__path__[0])\n"
        "env = gym.make('hireps/PendulumSwingUp-v0')\n"
        "assert type(env.unwrapped) is hireps_torch.envs.PendulumSwingUpEnv\n"
        "top = {m.split('.')[0] for m in sys.modules}\n"
        "assert not top & {'environments', 'experiments'}, top\n"
    )
    done = subprocess.run([str(python), "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    command = fresh / "bin" / "hireps-train"
    done = subprocess.run([str(command), "--help"], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0 and "pendulum" in done.stdout, done.stderr
