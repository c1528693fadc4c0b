"""One convention for every public function (issue 24, docs/api.md).

* Replacing an existing output is ``force``: a field of the job's options object where it has one
  (``ConvertOptions``, ``CrowdOptions``; ``build_crowd``'s old ``force=`` keyword still works), a
  keyword of a function without one (``decode``).
* Library errors speak to the caller of the function (``pass force=True``); the command line
  prints the same error with its own flags (``--force``, ``--allow-outside-paths``).
* ``help(vbusd.convert)`` and ``inspect.signature(vbusd.convert)`` describe the function (likewise
  ``vbusd.bake`` and ``vbusd.decode``): plain functions, no module shares their names.
"""

from __future__ import annotations

import inspect
import pydoc
import shutil
from pathlib import Path

import pytest

import vbusd
from vbusd.cli import main
from vbusd.format.errors import OptionsError

VALID = Path(__file__).parent / "fixtures" / "validate" / "valid" / "crossMatrix_float16"


@pytest.fixture
def character(tmp_path) -> Path:
    shutil.copytree(VALID, tmp_path / "character")
    return tmp_path / "character" / "asset.usda"


def test_crowd_options_carry_force_and_the_message_fits_the_library(tmp_path, character):
    out = tmp_path / "crowd.usda"
    vbusd.build_crowd([str(character)], out, vbusd.CrowdOptions(count=3))
    with pytest.raises(OptionsError) as caught:
        vbusd.build_crowd([str(character)], out, vbusd.CrowdOptions(count=3))
    assert "force=True" in caught.value.message and "--force" not in caught.value.message
    report = vbusd.build_crowd([str(character)], out, vbusd.CrowdOptions(count=5, force=True))
    assert report.instances == [5]
    report = vbusd.build_crowd([str(character)], out, vbusd.CrowdOptions(count=6), force=True)  # the old keyword
    assert report.instances == [6]


def test_the_command_line_says_its_own_flags(tmp_path, character, capsys):
    out = tmp_path / "crowd.usda"
    out.write_text("#usda 1.0\n")
    assert main(["crowd", str(character), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "force=True" not in err
    outside = tmp_path / "inner" / "crowd.usda"
    outside.parent.mkdir()
    assert main(["crowd", str(character), "-o", str(outside)]) == 2
    err = capsys.readouterr().err
    assert "--allow-outside-paths" in err and "allow_outside_paths=True" not in err


@pytest.mark.parametrize("job", ["convert", "decode"])
def test_every_job_that_writes_refuses_an_existing_output_in_the_library_s_words(tmp_path, character, job):
    out = tmp_path / "out.usda"
    out.write_text("#usda 1.0\n")
    with pytest.raises(OptionsError) as caught:
        if job == "convert":
            vbusd.convert(str(character), out, vbusd.ConvertOptions())
        else:
            vbusd.decode(str(character), out)
    assert "force=True" in caught.value.message and "--force" not in caught.value.message


def test_an_outside_path_refusal_names_the_keyword(tmp_path, character):
    crowd = tmp_path / "inner" / "crowd.usda"
    crowd.parent.mkdir()
    with pytest.raises(OptionsError) as caught:
        vbusd.build_crowd([str(character)], crowd)
    assert "allow_outside_paths=True" in caught.value.message and "--allow" not in caught.value.message
    vbusd.build_crowd([str(character)], crowd, vbusd.CrowdOptions(allow_outside_paths=True, count=2))


@pytest.mark.parametrize("name, function", [("convert", "vbusd.jobs.conversion.convert"), ("bake", "vbusd.baking.baker.bake"),
                                            ("decode", "vbusd.jobs.pointcache.decode")])
def test_help_and_signature_describe_the_function(name, function):
    import importlib

    module_name, _, attribute = function.rpartition(".")
    target = getattr(importlib.import_module(module_name), attribute)
    job = getattr(vbusd, name)
    assert job is target and inspect.isfunction(job)  # the function itself, not a module made callable
    first = inspect.getdoc(target).splitlines()[0]
    text = pydoc.render_doc(job, renderer=pydoc.plaintext)
    assert f"{attribute}{inspect.signature(target)}" in text, text[:600]
    assert first in text, text[:600]
