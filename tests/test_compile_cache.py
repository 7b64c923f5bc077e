"""Compiled kernels are cached in the user's cache folder, per build, unless the user chose one."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pipeline.compile_cache import CACHE_VARIABLE, persist_compile_cache


def test_the_cache_goes_to_the_users_cache_folder_named_by_the_build(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(CACHE_VARIABLE, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    folder = persist_compile_cache(torch.device("cpu"))
    assert folder.is_dir() and folder.parent == tmp_path / "gsplatam" / "inductor"
    assert torch.__version__.split("+")[0] in folder.name and folder.name.endswith("cpu")
    import os

    assert os.environ[CACHE_VARIABLE] == str(folder)


def test_a_folder_the_user_chose_is_kept(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    mine = tmp_path / "mine"
    monkeypatch.setenv(CACHE_VARIABLE, str(mine))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert persist_compile_cache(torch.device("cpu")) == mine
    assert not (tmp_path / "xdg").exists()
