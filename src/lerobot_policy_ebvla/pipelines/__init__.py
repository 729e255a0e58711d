"""Multi-step jobs built from the library, each the body of a console script.

- `column_queries`: LeRobot's training loader reading an action chunk from the action column alone (LeRobot
  0.6.1 decodes the frames of every chunk row of an image dataset); the quickstart trains inside it.
- `eval_energy`: LeRobot's evaluation with the energy of every refined chunk recorded (`ebvla-eval`), and the
  fast-render MetaWorld evaluation of a checkpoint that the quickstart and the benchmarks run.
- `landscape`: the energy landscape of a saved policy around one observation, as a PNG (`ebvla-landscape`).
- `quickstart`: record MetaWorld demonstrations, train the light policy, evaluate it in three conditions and
  summarise the energies (`ebvla-quickstart`).
"""
