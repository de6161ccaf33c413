"""Development tools, run from a checkout and left out of the wheel: the benchmarks of docs/results.md
(``python -m fieldlog.tools.dev.bench``, ``make bench``), the fuzzing campaigns (``python -m fieldlog.tools.dev.fuzz``),
the MCAP layouts other writers produce (``layouts``: the reader's tests and bench) and the README's screenshot
(``make screenshot``)."""
