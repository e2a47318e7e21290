"""benchmarks/readme_numbers.py, without measuring: every section has its README block, and
rewriting a block changes that block and nothing else."""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "readme_numbers.py"
_spec = importlib.util.spec_from_file_location("readme_numbers", SCRIPT)
readme_numbers = sys.modules["readme_numbers"] = importlib.util.module_from_spec(_spec)  # for its dataclasses
_spec.loader.exec_module(readme_numbers)


def test_every_section_has_its_block_in_the_readme_exactly_once():
    text = (ROOT / "README.md").read_text()
    for name in readme_numbers.SECTIONS:
        begin, end = readme_numbers.markers(name)
        assert text.count(begin) == 1 and text.count(end) == 1, name
        assert text.index(begin) < text.index(end), name
        readme_numbers.replace_block(text, name, "")  # each marker on a line of its own
    assert set(re.findall(r"<!-- /?numbers:([\w-]+) -->", text)) == set(readme_numbers.SECTIONS)


def test_rewriting_a_block_changes_that_block_only():
    text = ("intro\n<!-- numbers:a -->\nold a\n<!-- /numbers:a -->\nmiddle\n- item\n"
            "  <!-- numbers:b -->\n  old b\n\n  more\n  <!-- /numbers:b -->\n- next item\n")
    rewritten = readme_numbers.replace_block(text, "b", "new b\n\nline")
    assert rewritten == ("intro\n<!-- numbers:a -->\nold a\n<!-- /numbers:a -->\nmiddle\n- item\n"
                         "  <!-- numbers:b -->\n  new b\n\n  line\n  <!-- /numbers:b -->\n- next item\n")
    assert readme_numbers.replace_block(rewritten, "b", "old b\n\nmore") == text
    assert readme_numbers.replace_block(text, "a", "") == text.replace("old a\n", "")


@pytest.mark.parametrize("text", [
    "no markers at all\n",
    "<!-- numbers:a -->\nx\n<!-- /numbers:a -->\n<!-- numbers:a -->\ny\n<!-- /numbers:a -->\n",
    "<!-- /numbers:a -->\nx\n<!-- numbers:a -->\n",
    "inline <!-- numbers:a --> x <!-- /numbers:a --> text\n",
])
def test_a_missing_doubled_or_misplaced_block_is_refused(text):
    with pytest.raises(ValueError, match="numbers:a"):
        readme_numbers.replace_block(text, "a", "new")


def test_an_unknown_section_ends_in_one_line_and_exit_2():
    done = subprocess.run([sys.executable, str(SCRIPT), "speed", "nosuch"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == ["readme_numbers.py: unknown section nosuch (see --list)"]
