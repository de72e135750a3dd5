"""Reporting: everything people look at (report.md sections, figures, stage summaries), rendered
from data the other layers computed; nothing here computes a score."""
