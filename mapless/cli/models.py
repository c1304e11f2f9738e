"""``mapless models``: the registered navigation models."""

from __future__ import annotations

import argparse

from mapless.cli.common import add_category_set_argument, add_command


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("models", help="registered navigation models")
    sub = parser.add_subparsers(dest="models_command", required=True)
    listing = add_command(sub, "list", list_models, help="model names with parameter counts")
    add_category_set_argument(listing)
    listing.add_argument(
        "--reference",
        action="store_true",
        help="reference-sized inputs: 512-channel ResNet-18 maps and the originals' dead modules",
    )


def list_models(args: argparse.Namespace) -> int:
    # Imported here so that `mapless --help` does not pay for torch.
    from mapless.models import ModelConfig, build_model, count_parameters, model_names

    rows = []
    for name in model_names():
        config = ModelConfig(name=name, category_set=args.category_set)
        if args.reference:
            config = ModelConfig(
                name=name, category_set=args.category_set, feature_channels=512, reference_extras=True
            )
        model = build_model(config)
        trainable, total = count_parameters(model)
        inner = f"{model.inner_lr:g}" if model.adaptive else "-"
        rows.append((name, f"{trainable:,}", f"{total:,}", inner, model.description))
    header = ("model", "trainable", "total", "inner lr", "description")
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(4)]
    for row in [header, *rows]:
        print(
            "  ".join(
                cell.ljust(w) if i == 0 else cell.rjust(w)
                for i, (cell, w) in enumerate(zip(row[:4], widths, strict=True))
            )
            + "  "
            + row[4]
        )
    return 0
