"""Benchmarks whose markdown output goes into BENCHMARKS.md (``quasisim bench ...``)."""
