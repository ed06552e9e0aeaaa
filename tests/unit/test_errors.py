"""occtrain.errors: the line a person reads when something below occtrain refuses."""

from __future__ import annotations

import pytest

from occtrain.config.llm import LLMConfig
from occtrain.errors import cause_line
from occtrain.models.llm import tiny_config


def test_a_validator_that_only_introduces_its_cause_is_followed_to_it() -> None:
    """transformers refuses 3 heads over 128 through huggingface_hub's strict dataclasses,
    whose first line names the validator; the reason is the ValueError behind it."""
    with pytest.raises(Exception) as err:
        tiny_config(LLMConfig(num_heads=3), 100)  # occtrain's own check is bypassed: straight to transformers
    assert str(err.value).startswith("Class validation error for validator 'validate_architecture':")
    assert (
        cause_line(err.value)
        == "ValueError: The hidden size (128) is not a multiple of the number of attention heads (3)."
    )


def test_an_error_that_says_why_keeps_its_own_line() -> None:
    try:
        try:
            raise KeyError("w")
        except KeyError as inner:
            raise RuntimeError("probe exploded\nsecond line") from inner
    except RuntimeError as err:
        assert cause_line(err) == "RuntimeError: probe exploded"
