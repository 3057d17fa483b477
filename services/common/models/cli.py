"""``kmvipe models list`` and ``kmvipe models pull NAME``."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..errors import ModelError
from .registry import HubSource, all_entries, get_entry
from .store import MODELS_DIR_ENV, ModelStore, default_models_dir

log = logging.getLogger(__name__)

def register(subparsers) -> None:
    """Add ``models {list,pull}`` to the kmvipe CLI."""
    parser = subparsers.add_parser("models", help="list, check and download the models KM-ViPE uses")
    parser.add_argument(
        "--models-dir", type=Path, default=None, help=f"air-gapped models folder (default: ${MODELS_DIR_ENV})"
    )
    sub = parser.add_subparsers(dest="models_command", required=True)
    sub.add_parser("list", help="every registered model: installed where, or what it needs").set_defaults(
        func=handle_list
    )
    pull = sub.add_parser("pull", help="download a model from the Hugging Face hub")
    pull.add_argument("name", help="registry name or hub repo id (see 'kmvipe models list')")
    pull.set_defaults(func=handle_pull)


def _store(args: argparse.Namespace) -> ModelStore:
    return ModelStore(args.models_dir or default_models_dir())


def format_listing(store: ModelStore) -> str:
    """The table ``kmvipe models list`` prints."""
    lines = [f"{'name':40} {'kind':10} {'space':18} {'status'}"]
    for entry in all_entries():
        st = store.status(entry)
        src = entry.source
        origin = src.repo_id if isinstance(src, HubSource) else src.requirement
        state = f"installed ({st.location.origin}: {st.location.path})" if st.location else f"missing — {st.needs}"
        lines.append(f"{entry.name:40} {entry.kind.value:10} {entry.output_space:18} {state}")
        lines.append(f"{'':40} source {origin}; licence {entry.licence}")
    return "\n".join(lines)


def handle_list(args: argparse.Namespace) -> int:
    print(format_listing(_store(args)))
    return 0


def handle_pull(args: argparse.Namespace) -> int:
    store = _store(args)
    try:
        loc = store.pull(get_entry(args.name))
    except ModelError as exc:
        print(f"error: {exc}")
        return 1
    print(f"{loc.entry.name}: installed at {loc.path} ({loc.origin})")
    return 0
