"""Human-readable summaries the CLI prints after a step (the library returns data)."""

from __future__ import annotations


def report_select_views(result) -> str:
    from colmap_pvs.views import format_selection_table

    return format_selection_table(result)


def report_stereo(result) -> str:
    lines = [
        f"workspace: {result.workspace.root}",
        f"computed: {len(result.processed)}  already done: {len(result.already_done)}  "
        f"skipped: {len(result.skipped)}  seconds/image: {result.seconds_per_image:.2f}",
    ]
    if result.pass_seconds.get("geometric") is not None:  # the second pass
        lines.append(
            f"geometric pass: computed: {len(result.geometric_processed)}  already done: "
            f"{len(result.geometric_done)}  skipped: {len(result.geometric_skipped)}  "
            f"({result.pass_seconds['geometric']:.1f} s; "
            f"photometric {result.pass_seconds['photometric']:.1f} s)"
        )
    if result.adapt_seconds > 0:
        lines.append(
            f"test-time adaptation: {result.adapt_seconds:.1f} s "
            f"({result.adapt_seconds_per_image:.2f} s per reference image)"
        )
    lines += [f"  skipped {name}: {why}" for name, why in result.skipped.items()]
    return "\n".join(lines)


def report_checkpoint(result) -> str:
    """``train`` and ``average-weights``: the checkpoint written."""
    return f"checkpoint: {result}"
