"""Report stage: the results directory of a fit (``resultsdir``: ``results.json``, signal
tables, reading them back) and its HTML report (``html``; the jinja2 templates in
``templates/`` are package data of this package).

Public API::

    write_report(results_dir) -> Path
    dumps, finite_or_none, signals_table, read_results, contained_file
"""

from .html import new_figure, parse_reference, png_data_uri, write_report
from .resultsdir import contained_file, dumps, finite_or_none, read_results, signals_table

__all__ = ["contained_file", "dumps", "finite_or_none", "new_figure", "parse_reference",
           "png_data_uri", "read_results", "signals_table", "write_report"]
