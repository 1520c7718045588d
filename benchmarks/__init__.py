"""Speed and accuracy benchmarks: `python -m benchmarks.NAME [--quick]`.

Each prints a table and, as its very last line, one JSON object with its headline figures."""
