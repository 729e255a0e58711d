"""The research beside the package: experiment scripts, committed records, study docs and their tests.

Not installed (the package is `src/lerobot_policy_ebvla`); a package here only so that `research.tests` imports
under its own name beside the package's `tests`.
"""
