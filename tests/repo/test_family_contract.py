"""Every family with a world model, shipped or the test plugin, is held to the family
contract (tests/family_contract.py) by the end-to-end file that trains its tiny run."""

from __future__ import annotations

from conftest import REPO
from family_contract import HELD_BY
from occtrain.core.registry import world_families


def test_every_world_family_is_held_to_the_contract():
    families = set(world_families()) | {"tiny_columns"}  # the plugin's, registered only where imported
    assert families <= set(HELD_BY), f"hold {sorted(families - set(HELD_BY))} to it in family_contract.HELD_BY"
    for family, test_file in HELD_BY.items():
        text = (REPO / test_file).read_text()
        assert "def test_the_family_keeps_the_contract(" in text and "check_contract(" in text, (family, test_file)
