"""Orchestration: the steps that make an experiment's inputs (world, encoder, detector, tables, features), the
experiments and the demo as job lists with one marker convention, convergence runs and the release evaluation."""
