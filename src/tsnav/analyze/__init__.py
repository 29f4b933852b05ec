"""Analyses behind docs/RESULTS.md: ``tsnav analyze NAME ...`` (one module per analysis; :mod:`.command`).

They read what the pipeline wrote (evaluation folders, run folders, detection tables, results files) and print or
write tables and figures; none of them is a step of the pipeline, and nothing else in tsnav imports them.
"""
