"""Homework exercises that are not part of the solver: task 5 (`analysis`) of `python -m demo homework`."""
