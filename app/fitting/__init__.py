"""Fit jobs: the background runner (`runner`), the uploads (`uploads`) and Parquet datasets
(`datasets`) they fit, the first-start default profile (`bootstrap`) and automatic refits on
degraded feedback (`refit`)."""
