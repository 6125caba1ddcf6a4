"""Scenario spec loading and validation: TOML -> validated pydantic spec.

The spec format is described in ``docs/SCENARIO_FORMAT.md`` (and in the shared
DESIGN.md).  This package only validates; :mod:`contract.scene` compiles a
validated spec into the engine-neutral scene model that adapters consume.

Modules: ``schema`` (the pydantic model of each section), ``bounds`` (the
physical bounds), ``errors`` (SpecError and the wording of pydantic's
errors), ``overrides`` (dotted keys: variants and ``--set``), ``validate``
(schema, then the checks that span sections) and ``load`` (files and
variants).  The names other modules import stay importable from here.

Every error names the file, the key path and what was expected, e.g.::

    scenarios/billiards/head_on.toml: body[1].mass: must be > 0, got -1

Unknown keys, effects and shapes are errors.  Every number must be finite,
and physical quantities must lie within the bounds of :data:`BOUNDS`
(documented in the bounds table of ``docs/SCENARIO_FORMAT.md``; the test
``tests/test_fuzz.py::test_bounds_table_matches_docs`` keeps the two equal).
"""

from physbench.contract.spec.bounds import BOUNDS, record_size_error
from physbench.contract.spec.errors import ModelRefusal, SpecError, _format_errors
from physbench.contract.spec.load import LoadedSpec, _display, load_spec, read_toml
from physbench.contract.spec.overrides import parse_key_path, parse_value
from physbench.contract.spec.schema import SpecModel
from physbench.contract.spec.validate import validate_raw
