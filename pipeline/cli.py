"""Command line: ``pipeline run WORKFLOW`` and friends."""
from __future__ import annotations

import json
import sys

import click

from pipeline.config import WorkflowError
from stages import InputError


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """Machining-error prediction for mould finishing programs (see README)."""


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False), help="Output directory (default: workflow's `output`).")
@click.option("--scheduler", help="Address of an existing Dask scheduler (default: a LocalCluster).")
@click.option("--workers", type=click.IntRange(1, 256), help="Workers of the LocalCluster (default: CPU count).")
@click.option("--until", help="Stop after this stage.")
@click.option("--fresh", is_flag=True, help="Ignore and delete the cache of this output directory.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
def run(workflow, out, scheduler, workers, until, fresh, quiet):
    """Run WORKFLOW: only partitions not already in the cache are computed."""
    from pipeline.engine import Run
    try:
        r = Run(workflow, out=out, until=until, fresh=fresh)
        summary = r.execute(scheduler=scheduler, workers=workers, progress=not quiet)
    except (WorkflowError, InputError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    _print_summary(summary)
    sys.exit(1 if summary["failures"] else 0)


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def status(workflow, out, as_json):
    """Show which stages and partitions of WORKFLOW are done."""
    from pipeline.engine import Run
    try:
        rows = Run(workflow, out=out).status()
    except WorkflowError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    click.echo(f"{'stage':>12}  {'done':>6}  {'pending':>7}  {'blocked':>7}")
    for r in rows:
        click.echo(f"{r['stage']:>12}  {r['done']:>6}  {r['pending']:>7}  {r['blocked']:>7}")


def _print_summary(s: dict) -> None:
    c = s["counts"]
    click.echo(f"{s['name']}: {c['programs']} programs ({c['programs_failed']} failed), {c['passes']} passes, "
               f"{s['wall_s']:.2f} s -> {s['output']}")
    click.echo(f"{'stage':>12}  {'parts':>5}  {'cached':>6}  {'computed':>8}  {'failed':>6}  {'wall_s':>7}")
    for st in s["stages"]:
        click.echo(f"{st['name']:>12}  {st['partitions']:>5}  {st['cached']:>6}  {st['computed']:>8}  "
                   f"{st['failed']:>6}  {st['wall_s']:>7.3f}")
    if s["failures"]:
        click.echo(f"{len(s['failures'])} failure(s):", err=True)
        for f in s["failures"]:
            click.echo(f"  [{f['stage']}] {f['message']}", err=True)


if __name__ == "__main__":
    main()
