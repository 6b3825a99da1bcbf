"""Command line of the vehicle agent.

python -m agents run --config agent.json         run one vehicle's agent
python -m agents sim fleet --configs var/agents  run simulated vehicles with their agents
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import sys
from pathlib import Path

from agents.config import AgentConfig, ConfigError
from agents.runtime import agents_run_forever
from agents.vehicles.registry import UnknownIntegration, integration


def _load_fleet(folder: Path, only: list[str]) -> list[AgentConfig]:
    """The agent configs in ``folder`` whose adapter this installation has."""
    configs = []
    for path in sorted(folder.glob("*.json")):
        config = AgentConfig.load(path)
        if only and config.name not in only and path.stem not in only:
            continue
        try:
            integration(config.adapter)
        except UnknownIntegration:
            logging.warning("%s: no %r adapter here; not started", path.name, config.adapter)
            continue
        # A simulated fleet: every adapter on its simulator, control on a free port.
        options = {**config.adapter_options, "simulate": True}
        configs.append(dataclasses.replace(config, adapter_options=options))
    return configs


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # `sim KIND` for a vehicle simulator is handled by that simulator's own module.
    if len(argv) >= 2 and argv[0] == "sim" and argv[1] not in {"fleet", "-h", "--help"}:
        try:
            simulator = integration(argv[1]).simulator
        except UnknownIntegration:
            simulator = None
        if simulator is None:
            print(f"no simulator named {argv[1]!r}", file=sys.stderr)
            return 2
        module = importlib.import_module(simulator)
        return int(module.cli(argv[2:]))
    parser = argparse.ArgumentParser(
        prog="python -m agents",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--log-level", default="INFO")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="run one vehicle's agent")
    run.add_argument("--config", required=True, type=Path, help="the agent's JSON config")

    sim = commands.add_parser("sim", help="simulated vehicles with their agents")
    sim_kinds = sim.add_subparsers(dest="kind", required=True)
    fleet = sim_kinds.add_parser("fleet", help="one simulated agent per config file")
    sim_kinds.add_parser("KIND", help="a vehicle simulator: car_world, mavlink, spektrum, ...")
    fleet.add_argument("--configs", type=Path, default=Path("var/agents"))
    fleet.add_argument("--only", nargs="*", default=[], help="vehicle names to run")

    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        if args.command == "run":
            configs = [AgentConfig.load(args.config)]
        else:
            configs = _load_fleet(args.configs, args.only)
            if not configs:
                print(f"no agent configs in {args.configs}", file=sys.stderr)
                return 2
    except ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    agents_run_forever(configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
