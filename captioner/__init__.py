"""Instruction grammar, splits, rule captioner and the language-goal environment wrapper."""
