"""Agents: multi-turn rollouts in which the model calls tools between its turns."""
