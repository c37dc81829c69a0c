"""Small helpers for the text ermrl prints."""

from __future__ import annotations

__all__ = ["plural"]


def plural(n: int, noun: str, nouns: str | None = None) -> str:
    """``n`` and the noun, singular for exactly 1: ``plural(1, "seed") == "1 seed"``.

    Args:
        n: The count.
        noun: The singular form.
        nouns: The plural form (default: ``noun + "s"``).

    Examples:
        >>> plural(1, "trial"), plural(3, "trial"), plural(0, "run")
        ('1 trial', '3 trials', '0 runs')
    """
    return f"{n} {noun if n == 1 else (nouns or noun + 's')}"
