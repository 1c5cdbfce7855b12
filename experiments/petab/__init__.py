"""Three problems of the PEtab benchmark collection written as torchql models, with their likelihood.

Boehm_JProteomeRes2014, Bruno_JExpBot2016 and Fiedler_BMCSystBiol2016 (Hass et al. 2019,
Bioinformatics 35:3073), read from ``../shared/petab/<name>.json`` beside the repository. Each problem's
right-hand side, initial state, observables and noise are written by hand (:mod:`.boehm`, :mod:`.bruno`,
:mod:`.fiedler`); :mod:`.problem` reads the tables and builds each condition's simulation, and
:mod:`.likelihood` computes the PEtab negative log-likelihood from :func:`torchql.simulate`::

    from experiments.petab import PROBLEMS, load_problem, nominal_values, negative_log_likelihood
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"])
    negative_log_likelihood(problem, nominal_values(problem))   # -46.68818; reference -46.688177
"""

from .boehm import SPEC as BOEHM
from .bruno import SPEC as BRUNO
from .fiedler import SPEC as FIEDLER
from .likelihood import Simulator, likelihood_terms, negative_log_likelihood, row_terms, torchql_simulator
from .problem import (PETAB_DIR, ConditionSetup, PetabProblem, condition_symbols, load_problem, nominal_values,
                      setup_condition, values_from_scaled)
from .spec import ProblemSpec

#: The problems' specs by name.
PROBLEMS: dict[str, ProblemSpec] = {spec.name: spec for spec in (BOEHM, BRUNO, FIEDLER)}

__all__ = ["PROBLEMS", "ProblemSpec", "PetabProblem", "ConditionSetup", "Simulator", "PETAB_DIR", "load_problem",
           "nominal_values", "values_from_scaled", "condition_symbols", "setup_condition", "likelihood_terms",
           "negative_log_likelihood", "row_terms", "torchql_simulator"]
