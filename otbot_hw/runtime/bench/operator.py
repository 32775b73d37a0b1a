"""The person at the bench: told what to set up, asked to fix what a check found.

* ``PromptOperator`` (default, interactive): prints the instructions and waits for Enter on its
  input (``q`` stops the session, resumable; a closed input is an error: run with ``--yes`` for
  automation). With a simulated robot, lines typed at the prompt are operator commands for the
  simulated plant (``fixture stand``, ``load 40@0.2,-0.1,0.5``, ``unload``, ``status``:
  ``sim.plant.Plant.operator``): the person sets the simulated robot up themself; Enter without
  any command lets the simulated operator do what the instructions say.
* ``AutomaticOperator`` (``--yes``): no questions. With a simulated robot it does what the
  instructions say through the plant's operator channel; with a real robot it assumes the setup
  is done (the checks verify it). A failed check is final: nobody is there to fix it.
"""
from __future__ import annotations

import math
import sys
from typing import Callable, TextIO

#: std (kg) of a platform weighed on a bench scale (what the simulated operator's scale adds, and the std the
#: bench gives a typed weight without one)
SCALE_STD = 0.1
WEIGH_TEXT = ("weigh the unloaded platform (everything that turns with it, without the load) and give its mass in "
              "kg: a floor run sees only the chassis' and the platform's masses together (m_c + m_p0)")


class OperatorStopped(Exception):
    """The operator chose to stop (``q``): the session is kept and can be resumed."""


class NoOperator(Exception):
    """The operator's input closed while an answer was needed."""


class Operator:
    """Base: ``plant`` (a simulated plant with ``operator(command) -> dict``, or None) and what each
    step's setup means for it (``setup_commands(step)``)."""

    def __init__(self, plant=None, load: str | None = None, say: Callable[[str], None] | None = None):
        self.plant = plant
        self.load = load
        self.say = say or (lambda m: print(m, file=sys.stderr, flush=True))

    def setup_commands(self, fixture: str, loaded: bool) -> list[str]:
        """Operator-channel commands that set the simulated robot up for a step."""
        return [f"fixture {fixture}", (f"load {self.load}" if (loaded and self.load) else "unload")]

    def _do(self, commands: list[str]) -> None:
        for c in commands:
            reply = self.plant.operator(c)
            if "error" in reply:
                raise ValueError(f"simulated operator: {reply['error']}")
        self.say(f"[bench] simulated operator: {'; '.join(commands)}")

    def set_up(self, step: str, text: str, fixture: str, loaded: bool) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def weigh_platform(self, seed: int = 0) -> dict | None:  # pragma: no cover - interface
        """The unloaded platform's mass as measured at the bench, ``{value, std, source}`` (kg), or None."""
        raise NotImplementedError

    def _scale(self, seed: int) -> dict:
        """The simulated operator weighs the simulated platform (without its load): a bench scale of
        ``SCALE_STD`` read through the plant's operator channel (``status``)."""
        import numpy as np

        reply = self.plant.operator("status")
        if "error" in reply:
            raise ValueError(f"simulated operator: {reply['error']}")
        mass = float(reply["params"]["platform"]["m_p"]["value"])
        if reply.get("load"):
            mass -= float(_load_mass(reply["load"]))
        value = mass + SCALE_STD * float(np.random.default_rng([21, seed]).standard_normal())
        self.say(f"[bench] simulated operator: weighed the unloaded platform: {value:.2f} kg")
        return {"value": round(value, 2), "std": SCALE_STD, "source": "weighed (simulated scale)"}

    def retry(self, step: str, failed: list, fixture: str, loaded: bool) -> bool:  # pragma: no cover
        raise NotImplementedError


class AutomaticOperator(Operator):
    """``--yes``: the instructions are printed and, on a simulated robot, carried out."""

    def set_up(self, step: str, text: str, fixture: str, loaded: bool) -> None:
        self.say(f"[bench] {step}: {text}")
        if self.plant is not None:
            self._do(self.setup_commands(fixture, loaded))

    def retry(self, step: str, failed: list, fixture: str, loaded: bool) -> bool:
        return False

    def weigh_platform(self, seed: int = 0) -> dict | None:
        """The simulated robot is weighed; a real one with ``--yes`` is not (nobody to ask)."""
        self.say(f"[bench] {WEIGH_TEXT}")
        return self._scale(seed) if self.plant is not None else None


class PromptOperator(Operator):
    """Interactive: instructions, then a prompt on ``stream`` (default stdin)."""

    def __init__(self, plant=None, load: str | None = None, say=None, stream: TextIO | None = None):
        super().__init__(plant, load, say)
        self.stream = stream if stream is not None else sys.stdin

    def _answer(self) -> str:
        """The operator's next line, stripped ('' for Enter); input closed: ``NoOperator``; q: ``OperatorStopped``."""
        line = self.stream.readline()
        if not line:
            raise NoOperator("no answer from the operator (input closed); run interactively, or with --yes "
                             "for automation")
        words = line.strip()
        if words.lower() in ("q", "quit"):
            raise OperatorStopped("stopped by the operator")
        return words

    def _ask(self, prompt: str, fixture: str, loaded: bool) -> None:
        typed = False
        while True:
            self.say(prompt)
            words = self._answer()
            if not words:
                if self.plant is not None and not typed:
                    self._do(self.setup_commands(fixture, loaded))
                return
            if self.plant is None:
                self.say("[bench] (press Enter when done, q to stop)")
                continue
            reply = self.plant.operator(words)
            typed = typed or "error" not in reply
            self.say(f"[bench] simulated robot: {reply.get('error') or ({k: reply[k] for k in ('fixture', 'load')})}")

    def _prompt(self) -> str:
        sim = (" (simulated robot: type operator commands - fixture stand|locked|floor, load KG@X,Y[,I], unload - "
               "or just Enter to have it done as instructed)") if self.plant is not None else ""
        return f"[bench] press Enter when done, q to stop{sim}: "

    def set_up(self, step: str, text: str, fixture: str, loaded: bool) -> None:
        self.say(f"[bench] {step}: {text}")
        self._ask(self._prompt(), fixture, loaded)

    def weigh_platform(self, seed: int = 0) -> dict | None:
        """Ask for the weight: ``KG`` or ``KG+-STD``; ``n``: it cannot be weighed; Enter: the simulated operator
        weighs a simulated robot, a real one is not weighed; ``q`` stops. A bad answer is asked again."""
        self.say(f"[bench] {WEIGH_TEXT}")
        while True:
            sim = ", Enter to have the simulated operator weigh it" if self.plant is not None else \
                ", Enter if it cannot be weighed (the bench then reports what the recordings can tell)"
            self.say(f"[bench] platform mass in kg (KG or KG+-STD{sim}; n: cannot be weighed; q to stop): ")
            words = self._answer()
            if not words:
                return self._scale(seed) if self.plant is not None else None
            if words.lower() in ("n", "no"):
                return None
            try:
                value, _, std = words.partition("+-")
                v, sd = float(value), (float(std) if std.strip() else SCALE_STD)
                if not (math.isfinite(v) and v > 0 and math.isfinite(sd) and sd > 0):
                    raise ValueError
            except ValueError:
                self.say(f"[bench] {words!r} is not a mass in kg (a number > 0, optionally +-STD > 0)")
                continue
            return {"value": v, "std": sd, "source": "weighed (typed by the operator)"}

    def retry(self, step: str, failed: list, fixture: str, loaded: bool) -> bool:
        for c in failed:
            self.say(f"[bench] {step}: check {c.name} failed: {c.message}; {c.fix}")
        self._ask("[bench] fix it, then " + self._prompt()[len("[bench] "):], fixture, loaded)
        return True


def _load_mass(load) -> float:
    """Mass (kg) of the load in a plant's ``status`` reply (a dict with ``mass`` or a sequence)."""
    if isinstance(load, dict):
        return float(load.get("mass", load.get("kg", 0.0)))
    return float(load[0])
