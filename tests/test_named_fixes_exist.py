"""Every fix an error message or the documentation names exists for the command that would take it: each
``--pipeline.*`` option is a field of ``ns-train gsmsdr``'s config (or of one of our dataparsers' configs), and
each ``--flag`` a message gives beside one of our ``gsmsdr-*`` commands is in that command's ``--help``."""

from __future__ import annotations

import ast
import dataclasses
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Dict, Iterator, List, Set, Tuple

import gsmsdr_ns

ROOT = Path(gsmsdr_ns.__file__).resolve().parent.parent
PIPELINE_OPTION = re.compile(r"--(pipeline\.[a-z0-9._-]*[a-z0-9_-])")
COMMAND = re.compile(r"\b(gsmsdr-(?:synth|bench|degrade|estimate|process|export|eval))\b")
BOUNDARY = re.compile(r"\bgsmsdr-[a-z]+\b|\bns-[a-z]+\b|\bpython\b|\{\}")
"""Where one command's flags end: another command, a Python module run, or an f-string's replacement field."""
BENCH_SUBCOMMANDS = ("raster", "kernels", "degrade", "memory", "sfm", "suite", "step", "eta")
FLAG = re.compile(r"(?<![\w-])--([a-z][a-z0-9-]*[a-z0-9])\b")


def string_literals(path: Path) -> Iterator[str]:
    """Every string literal of a Python file, f-strings with their replacement fields as ``{}``."""
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.value
        elif isinstance(node, ast.JoinedStr):
            yield "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)


def package_sources() -> List[Path]:
    return sorted((ROOT / "gsmsdr_ns").rglob("*.py"))


def documents() -> List[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def resolves(config: object, parts: List[str]) -> bool:
    """Whether ``a.b.c`` (tyro's dashed names) names a field path of the dataclass ``config``; a path ending in a
    nested config (a prefix such as ``blur-field.``) counts."""
    for part in parts:
        names = {f.name for f in dataclasses.fields(config)} if dataclasses.is_dataclass(config) else set()
        name = part.replace("-", "_")
        if name not in names:
            return False
        config = getattr(config, name)
    return True


@lru_cache(maxsize=1)
def dataparser_configs() -> Tuple[object, ...]:
    from gsmsdr_ns.plugin.dataparser_registration import deblur_nerf_data, gsmsdr_data, mixres_data
    from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

    registered = tuple(spec.config for spec in (deblur_nerf_data, mixres_data, gsmsdr_data))
    return (gsmsdr_trainer_config().pipeline.datamanager.dataparser, *registered)


def pipeline_option_exists(option: str) -> bool:
    from gsmsdr_ns.plugin.method_config import gsmsdr_lite_trainer_config, gsmsdr_trainer_config

    parts = option.split(".")[1:]
    if parts[:2] == ["datamanager", "dataparser"]:
        return any(resolves(config, parts[2:]) for config in dataparser_configs())
    return any(resolves(make().pipeline, parts) for make in (gsmsdr_trainer_config, gsmsdr_lite_trainer_config))


def named_pipeline_options() -> Dict[str, Set[str]]:
    """option -> the files that name it."""
    found: Dict[str, Set[str]] = {}
    texts = [(p, t) for p in package_sources() for t in string_literals(p)] + [(p, p.read_text()) for p in documents()]
    for path, text in texts:
        for option in PIPELINE_OPTION.findall(text):
            found.setdefault(option, set()).add(str(path.relative_to(ROOT)))
    return found


def test_every_pipeline_option_named_in_messages_and_docs_exists():
    named = named_pipeline_options()
    assert len(named) >= 20  # the scan finds the options (a broken pattern would pass vacuously)
    missing = {option: sorted(files) for option, files in named.items() if not pipeline_option_exists(option)}
    assert missing == {}, "these --pipeline options do not exist in ns-train gsmsdr's config"


def test_the_option_check_refuses_what_does_not_exist():
    assert pipeline_option_exists("pipeline.model.degradation-model.camera-shake")
    assert pipeline_option_exists("pipeline.model.blur-field")
    assert not pipeline_option_exists("pipeline.model.blur-field.camera-shake")  # moved to degradation-model
    assert pipeline_option_exists("pipeline.datamanager.dataparser.refuse-copied-test-views")
    assert not pipeline_option_exists("pipeline.datamanager.dataparser.no-such-option")


def command_flags_in_messages() -> Dict[Tuple[str, str], Set[str]]:
    """(command, flag) -> the files whose string (or README / docs line) gives ``flag`` right after naming
    ``command``: between the name and the next command, ``python`` or f-string field (whose flags are not the
    command's), in one sentence or inline code span. ``command`` includes a ``gsmsdr-bench`` subcommand."""
    found: Dict[Tuple[str, str], Set[str]] = {}
    texts = [(p, t) for p in package_sources() for t in string_literals(p)] + [(p, p.read_text()) for p in documents()]
    for path, text in texts:
        for sentence in re.split(r"(?<=[.;])\s|\n|`", text):
            marks = list(BOUNDARY.finditer(sentence))
            for mark, following in zip(marks, [*marks[1:], None]):
                command = COMMAND.fullmatch(mark.group())
                if command is None:
                    continue
                words = sentence[mark.end() : following.start() if following else len(sentence)]
                name = command.group(1)
                sub = re.match(r"\s+([a-z]+)\b", words)
                if name == "gsmsdr-bench" and sub and sub.group(1) in BENCH_SUBCOMMANDS:
                    name += " " + sub.group(1)
                for flag in FLAG.findall(words):
                    found.setdefault((name, flag), set()).add(str(path.relative_to(ROOT)))
    return found


@lru_cache(maxsize=None)
def help_text(command: str) -> str:
    program, *sub = command.split()
    script = Path(sys.executable).parent / program
    proc = subprocess.run([str(script), *sub, "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_every_flag_a_message_or_the_docs_give_for_one_of_our_commands_exists():
    named = command_flags_in_messages()
    assert len(named) >= 10
    with ThreadPoolExecutor(max_workers=4) as pool:  # each --help is mostly interpreter start-up
        list(pool.map(help_text, sorted({command for command, _ in named})))
    missing = {
        f"{command} --{flag}": sorted(files)
        for (command, flag), files in sorted(named.items())
        if not re.search(rf"--{re.escape(flag)}\b", help_text(command))
    }
    assert missing == {}, "these flags are not in the command's --help"
