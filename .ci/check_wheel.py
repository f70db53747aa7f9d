"""Run the README quickstart against an installed torchpf, from the current (empty) folder.

Usage: ``python .ci/check_wheel.py README.md`` with the python of a venv where the wheel is installed; fails
when torchpf is imported from a source tree instead of site-packages, when a console script is missing, or
when the quickstart raises.
"""

import os
import re
import shutil
import subprocess
import sys
import sysconfig


def quickstart(readme: str) -> str:
    """The first ```python block of the README's "## Quickstart" section."""
    with open(readme, encoding="utf-8") as f:
        text = f.read()
    section = text[text.index("## Quickstart") :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    if match is None:
        raise SystemExit(f"{readme}: no python block under '## Quickstart'")
    return match.group(1)


def main() -> None:
    import torchpf

    site = sysconfig.get_paths()["purelib"]
    if not os.path.abspath(torchpf.__file__).startswith(os.path.abspath(site)):
        raise SystemExit(
            f"torchpf is imported from {torchpf.__file__}, not from the installed wheel in {site}"
        )
    scripts = os.path.dirname(sys.executable)
    for name in ("torchpf", "torchpf-train"):
        exe = shutil.which(name, path=scripts)
        if exe is None:
            raise SystemExit(f"console script {name!r} is not installed in {scripts}")
        out = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True).stdout.strip()
        if out != f"torchpf {torchpf.__version__}":
            raise SystemExit(f"{name} --version printed {out!r}, expected 'torchpf {torchpf.__version__}'")
    code = quickstart(sys.argv[1])
    with open("quickstart.py", "w", encoding="utf-8") as f:
        f.write(code)
    subprocess.run([sys.executable, "quickstart.py"], check=True)
    print(
        f"check-wheel: torchpf {torchpf.__version__} from {os.path.dirname(torchpf.__file__)}: quickstart ran"
    )


if __name__ == "__main__":
    main()
