"""Command line of the vehicle agent.

python -m agents run --config agent.json         run one vehicle's agent, on its hardware
python -m agents sim fleet --configs var/agents  run simulated vehicles with their agents
python -m agents sim NAME [ARGS]                 run one integration's simulator on its own
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from agents.config import AgentConfig, ConfigError
from agents.runtime import agents_run_forever
from agents.vehicles.registry import UnknownIntegration, integration, integration_names


def _checked(config: AgentConfig, source: Path) -> AgentConfig:
    """``config`` if its adapter is installed and its options are good; else ConfigError
    naming the file and the option."""
    try:
        integration(config.adapter).commands(config.adapter_options)
    except UnknownIntegration as exc:
        raise ConfigError(f"{source}: adapter: {exc}") from None
    except ValueError as exc:
        raise ConfigError(f"{source}: adapter_options: {exc}") from None
    return config


def _load_fleet(folder: Path, only: list[str]) -> list[AgentConfig]:
    """The agent configs in ``folder`` (those named in ``only``, if given) whose adapter
    this installation has."""
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
        configs.append(_checked(config, path))
    return configs


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # `sim NAME` hands its arguments to that integration's simulator untouched.
    if len(argv) >= 2 and argv[0] == "sim" and argv[1] not in {"fleet", "-h", "--help"}:
        # Imported here, and only here: `run` on a vehicle never loads a simulator.
        from agents.simulation import simulator_cli

        # No logging set up here: each simulator's command line sets up its own.
        return simulator_cli(argv[1], argv[2:])
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
    sim_kinds.add_parser(
        "NAME", help=f"an integration's simulator: {', '.join(integration_names())}"
    )
    fleet.add_argument("--configs", type=Path, default=Path("var/agents"))
    fleet.add_argument("--only", nargs="*", default=[], help="vehicle names to run")

    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        if args.command == "run":
            configs = [_checked(AgentConfig.load(args.config), args.config)]
        else:
            configs = _load_fleet(args.configs, args.only)
            if not configs:
                print(f"no agent configs in {args.configs}", file=sys.stderr)
                return 2
    except ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    if args.command == "run":
        agents_run_forever(configs)
    else:
        from agents.simulation import fleet_run_forever

        fleet_run_forever(configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
