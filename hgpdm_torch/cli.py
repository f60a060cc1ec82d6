"""The ``hgpdm`` command: ``hgpdm demo`` and one subcommand per experiment.

Each subcommand is a module exposing ``main(argv: list[str]) -> int``; modules are imported only
when their command runs, so ``hgpdm --help`` stays fast and optional extras stay optional.
"""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["COMMANDS", "main"]

# command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": (
        "hgpdm_torch.experiments.demo",
        "the anticipatory table-tennis player end to end (Ch. 3-4, SAPIEN)",
    ),
    "style-discovery": (
        "hgpdm_torch.experiments.style_discovery",
        "fit an H-GPDM on synthetic styles and discover them (Sec. 2.2, Algorithm 2.1)",
    ),
    "action-recognition": (
        "hgpdm_torch.experiments.action_recognition",
        "action recognition on BasicMotions or MSRC-12 Kinect skeletons (Sec. 3.6, Table 3.3)",
    ),
    "anticipation": (
        "hgpdm_torch.experiments.anticipation",
        "Ch. 4 anticipatory action selection in table tennis: LSPI, MCP, NAC (Fig. 4.6-4.7)",
    ),
    "style-recognition": (
        "hgpdm_torch.experiments.style_recognition",
        "VB style recognition, forecasting and gap recovery (Sec. 2.4, Tables 2.1-2.4, Fig. 2.3)",
    ),
    "walkers": (
        "hgpdm_torch.experiments.walkers",
        "CMU Walkers / Weird Walking: VB recognition and pose forecasts (Tables 2.1-2.4)",
    ),
    "gap-recovery": (
        "hgpdm_torch.experiments.gap_recovery",
        "CMU Four Walkers: recovery of 31 missing frames (Sec. 2.4.1, Table 2.5)",
    ),
    "target-prediction": (
        "hgpdm_torch.experiments.target_prediction",
        "table-tennis target prediction (Sec. 3.5, Table 3.2, Fig. 3.7)",
    ),
    "games": (
        "hgpdm_torch.experiments.repeated_games",
        "Ch. 5 repeated games: delta-safe play in RPS and table-tennis serves (Fig. 5.1-5.7)",
    ),
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``hgpdm`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="hgpdm",
        description="hgpdm-torch: H-GPDM models, intention inference and decision making.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, text) in COMMANDS.items():
        sub.add_parser(name, help=text, add_help=False)
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    if argv[0] not in COMMANDS:
        parser.error(f"unknown command {argv[0]!r}; expected one of {', '.join(COMMANDS)}")
    module = importlib.import_module(COMMANDS[argv[0]][0])
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
