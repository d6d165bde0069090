"""Synthetic data: the sphere wake (an analytic flow refined by Berger-Rigoutsos), the analytic
fields of the tests, and the data files the repository's scenes refer to."""
