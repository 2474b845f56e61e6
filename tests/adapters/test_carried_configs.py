"""A carried tokenizer or processor config that names a file outside its folder (issue 42, item 3).

transformers opens a tokenizer's ``*_file`` arguments (``tokenizer_file``, ``vocab_file``, ...) as paths:
a pi0 bundle's ``lerobot/tokenizer/tokenizer_config.json`` naming ``"tokenizer_file":
"/abs/path/tokenizer.json"`` made that unhashed file decide the token ids, with no key and no flag. The
checks run where prop reads a VLA's tokenizer or VLM folder (``pi0.check_tokenizer``, ``smolvla.check_vlm``),
on bundles and on the folders personalize reads alike; these tests need no LeRobot (the end-to-end pi0 one
is in test_lerobot_pi0.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from prop_adapters.lerobot.pi0 import check_tokenizer
from prop_adapters.lerobot.smolvla import check_vlm
from prop_cli.errors import PropError

FIXTURE_VLM = Path(__file__).parents[1] / "fixtures/bundles-0.1/lerobot-smolvla-sealed/bundle/lerobot/vlm"


def _tokenizer(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "tokenizer.json").write_text(json.dumps({"model": {"vocab": {"load_file": 1, "x_files": 2}}}))
    (folder / "tokenizer_config.json").write_text(json.dumps({"bos_token": "<bos>", "tokenizer_file": None}))
    return folder


def _edit(folder: Path, name: str, **fields) -> None:
    doc = json.loads((folder / name).read_text())
    doc.update(fields)
    (folder / name).write_text(json.dumps(doc))


@pytest.mark.parametrize(
    "value",
    ["/abs/path/tokenizer.json", "../../elsewhere/tokenizer.json", "tokenizer.json", "sub/tokenizer.json", 3],
)
def test_a_tokenizer_config_naming_a_file_is_refused(tmp_path, value):
    """Absolute, relative, or a plain name (transformers reads it from the working folder, not the
    tokenizer's: measured with transformers 5.5, a swapped tokenizer.json in the working folder set the
    ids), or a number (an open file descriptor): refused in one line naming the file, field and value."""
    tok = _tokenizer(tmp_path / "tokenizer")
    assert check_tokenizer(tok, "pi0", "bundle b") == tok  # words ending in _file in the vocabulary: data
    _edit(tok, "tokenizer_config.json", tokenizer_file=value)
    with pytest.raises(PropError) as e:
        check_tokenizer(tok, "pi0", "bundle b")
    line = str(e.value)
    assert "\n" not in line and "tokenizer_config.json names tokenizer_file" in line and repr(value) in line
    assert "outside tokenizer/" in line and "leave tokenizer_file out" in line


@pytest.mark.parametrize(
    "name,field,value",
    [
        ("tokenizer_config.json", "vocab_file", "/etc/passwd"),
        ("processor_config.json", "chat_template_file", "../chat.jinja"),
        ("preprocessor_config.json", "image_processor", {"nested": {"config_file": "x.json"}}),
        ("tokenizer_config.json", "fast_tokenizer_files", ["../tokenizer.4.0.json"]),
        ("tokenizer_config.json", "fast_tokenizer_files", ["tokenizer.missing.json"]),
    ],
)
def test_a_vlm_config_naming_a_file_outside_its_folder_is_refused(tmp_path, name, field, value):
    """SmolVLA's carried vlm/ (the 0.1 fixture's files): any *_file field with a value, at any depth, and
    a *_files list naming anything but a file beside it, in any of the settings files transformers reads."""
    vlm = tmp_path / "vlm"
    shutil.copytree(FIXTURE_VLM, vlm)
    assert check_vlm(vlm, "bundle b") == vlm
    _edit(vlm, name, **{field: value})
    with pytest.raises(PropError, match=rf"SmolVLA's VLM file .*{name} names \w+_files? ") as e:
        check_vlm(vlm, "bundle b")
    assert "\n" not in str(e.value)


def test_a_files_list_naming_files_beside_it_is_kept(tmp_path):
    """transformers looks a *_files entry up in the folder itself: a plain name of a file there passes."""
    vlm = tmp_path / "vlm"
    shutil.copytree(FIXTURE_VLM, vlm)
    _edit(vlm, "tokenizer_config.json", fast_tokenizer_files=["tokenizer.json"], tokenizer_file=None)
    assert check_vlm(vlm, "bundle b") == vlm
    (vlm / "linked.json").symlink_to(tmp_path / "vlm" / "tokenizer.json")
    _edit(vlm, "tokenizer_config.json", fast_tokenizer_files=["linked.json"])
    with pytest.raises(PropError, match="fast_tokenizer_files"):
        check_vlm(vlm, "bundle b")
