"""The README's benchmark tables are what ``bench/results/`` gives (``bench/readme_tables.py``):
a hand edit of a number, or new results without regenerating the README, fails here."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "bench" / "readme_tables.py"


def check(readme):
    return subprocess.run([sys.executable, str(SCRIPT), "--check", "--readme", str(readme)],
                          capture_output=True, text=True, cwd=REPO)


def test_readme_tables_equal_the_results():
    done = check(REPO / "README.md")
    assert done.returncode == 0, done.stderr


def test_a_hand_edited_number_is_caught_and_regenerated(tmp_path):
    text = (REPO / "README.md").read_text()
    edited = text.replace("| 0.288 |", "| 0.289 |", 1)
    assert edited != text
    readme = tmp_path / "README.md"
    readme.write_text(edited)
    done = check(readme)
    assert done.returncode == 1
    assert "differ" in done.stderr
    subprocess.run([sys.executable, str(SCRIPT), "--readme", str(readme)], check=True,
                   capture_output=True, cwd=REPO)
    assert readme.read_text() == text
