"""``gonio verify SESSION``: argument to call (`gonio.bench.session.verify.verify_session`) and print.

Exit status 0: every measured point intact; 1: damage found (the report says how to recover);
2: not a session, an unreadable session.toml, or a capture measuring into it.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["verify_cli"]


def verify_cli(session: str) -> int:
    """Print the verdict on ``session``; return the exit status."""
    from gonio.bench.session.verify import verify_session

    verdict = verify_session(Path(session))
    print("\n".join(verdict.lines()), flush=True)
    return 0 if verdict.ok else 1
