"""The outcome of an identification: the Identification, its documents,
text, report and predictions."""
