"""Locating the shared data folder (docs/dataset.md, "Where the data live")."""
import pytest

from estcal.kinematics import robots


def test_env_variable_wins(tmp_path, monkeypatch):
    monkeypatch.setenv("ESTCAL_SHARED", str(tmp_path))
    assert robots.shared_dir() == tmp_path


def test_working_folder_is_searched(tmp_path, monkeypatch):
    """A non-editable install cannot find shared/ from the package location; ./shared is used."""
    monkeypatch.delenv("ESTCAL_SHARED", raising=False)
    (tmp_path / "shared").mkdir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(robots, "__file__", str(tmp_path / "venv" / "lib" / "site" / "estcal" / "kinematics" / "robots.py"))
    assert robots.shared_dir() == tmp_path / "shared"


def test_missing_tiago_message_names_folders_and_variable(tmp_path, monkeypatch):
    monkeypatch.setenv("ESTCAL_SHARED", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match=r"ESTCAL_SHARED.*--save-model|searched: .*nowhere"):
        robots.tiago()
