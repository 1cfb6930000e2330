"""Runge–Kutta methods as data: one frozen `ButcherTableau` per method, each with its source.

`METHODS` maps the names that `solve(method=...)` and `SolverOptions.method` accept to the
tableaus. This module is plain Python (no torch), so the options and the CLI can list the
methods without importing torch; `runge_kutta.StageTableau` turns a tableau into tensors.

- **tsit5** (default): Ch. Tsitouras, "Runge–Kutta pairs of order 5(4) satisfying only the
  first column simplifying assumption", Computers & Mathematics with Applications 62 (2011)
  770–775. The digits are those of OrdinaryDiffEq.jl,
  `lib/OrdinaryDiffEqTsit5/src/tsit_tableaus.jl` (`Tsit5ConstantCacheActual`, the
  high-precision method, and `Tsit5Interp` for dense output), rounded to float64 by
  Python's parser.
- **dopri5**: J. R. Dormand & P. J. Prince, "A family of embedded Runge–Kutta formulae",
  J. Comput. Appl. Math. 6 (1980) 19–26 (also Hairer, Nørsett & Wanner, Solving ODEs I,
  §II.5). Dense output: the 4th-order continuous extension of L. F. Shampine,
  "Some practical Runge–Kutta formulas", Math. Comp. 46 (1986) 135–150, with the
  coefficients of scipy's `RK45.P` (`scipy/integrate/_ivp/rk.py`).
- **rk4**: the classic 4th-order method (W. Kutta, Z. Math. Phys. 46 (1901) 435–453;
  Hairer, Nørsett & Wanner I, §II.1). It has no error estimate, so it only takes fixed
  steps; its dense output is the cubic Hermite interpolant of the step's end values and
  derivatives (ibid. §II.6).

Two Tsit5 traps, both avoided here:
- The paper's Table 1 lists b̂ − b (not b̂) with the wrong sign on the 7th entry
  (OrdinaryDiffEq.jl#1654, diffrax#98, SUNDIALS PR #850). Tsit5's e below is e = b − b̂
  taken from OrdinaryDiffEq.jl (where `btilde = −e`), not from the paper.
- torchdiffeq's unreleased `tsit5` propagates b̂ (4th order). We propagate b (5th order,
  local extrapolation), and the FSAL stage k7 = f(t + h, y_new) is then the derivative at
  the point we actually advance to. Dopri5 is used the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction


@dataclass(frozen=True)
class ButcherTableau:
    """An explicit Runge–Kutta method with s stages, its error weights and dense output.

    Attributes:
        name: registry name (`solve(method=name)`).
        summary: a few words for help texts ("Tsitouras 5(4), adaptive").
        c: `(s,)` nodes c_i.
        a: `(s,)` rows of the strictly lower-triangular a_ij; row i holds a_i1 .. a_i,i-1
            (row 0 is empty).
        b: `(s,)` weights of the propagated solution.
        e: `(s,)` error weights e = b − b̂ (the sign convention of diffrax `b_error` and
            torchode `b_err`; scipy's `E` is −e), or None for a method without an embedded
            pair, which then only takes fixed steps.
        interp: dense output y(t₀ + θh) = y₀ + h Σ_i b_i(θ) k_i, with
            b_i(θ) = Σ_j interp[i][j] θ^(j+1) (no constant term, so b_i(0) = 0, and
            b_i(1) = b_i). One row per stage and, for a method that is not FSAL, one more
            row for the derivative at the step's end, f(t₀ + h, y₁), which the solver
            computes after every step anyway (it is the next step's k₁).
        order: p, the order of the propagated solution.
        error_order: order of the embedded solution b̂ (None without one).
        dense_order: q, the order of the interpolant (local error O(h^(q+1))).
        fsal: first same as last: c_s = 1, row s of a equals b and b_s = 0, so the last
            stage is f(t₀ + h, y₁).
    """

    name: str
    summary: str
    c: tuple[float, ...]
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    e: tuple[float, ...] | None
    interp: tuple[tuple[float, ...], ...]
    order: int
    error_order: int | None
    dense_order: int
    fsal: bool

    def __post_init__(self):
        s = len(self.c)
        if len(self.a) != s or len(self.b) != s or (self.e is not None and len(self.e) != s):
            raise ValueError(f"{self.name}: c, a, b and e need one entry per stage")
        if any(len(row) != i for i, row in enumerate(self.a)):
            raise ValueError(f"{self.name}: row i of a holds a_i1 .. a_i,i-1")
        if len(self.interp) != s + (not self.fsal):
            raise ValueError(f"{self.name}: interp needs a row per stage (and one for the "
                             "end derivative unless FSAL)")
        if self.fsal and not (self.c[-1] == 1.0 and self.a[-1] == self.b[:-1]
                              and self.b[-1] == 0.0):
            raise ValueError(f"{self.name}: an FSAL method has c_s = 1, a_s = b, b_s = 0")
        if (self.e is None) != (self.error_order is None):
            raise ValueError(f"{self.name}: e and error_order come together")

    @property
    def stages(self) -> int:
        """s, the number of stages."""
        return len(self.c)

    @property
    def adaptive(self) -> bool:
        """Whether the method has an error estimate (and so can choose its step sizes)."""
        return self.e is not None

    @property
    def controller_order(self) -> int:
        """The exponent base of step-size control: the error estimate's order + 1."""
        if self.error_order is None:
            raise ValueError(f"method '{self.name}' has no error estimate")
        return self.error_order + 1


# ---- Tsit5 (digits of OrdinaryDiffEq.jl, see above)

# Nodes c_i (7 stages; c6 = c7 = 1, FSAL).
_TSIT5_C = (
    0.0,
    0.161,
    0.327,
    0.9,
    0.9800255409045096857298102862870245954942137979563024768854764293221195950761080302604,
    1.0,
    1.0,
)

# Strictly lower-triangular a_ij, row by row (row i holds a_i1 .. a_i,i-1); row 7 equals B
# (added below).
_TSIT5_A = (
    (),
    (0.161,),
    (
        -0.8480655492356988544426874250230774675121177393430391537369234245294192976164141156943e-2,
        0.3354806554923569885444268742502307746751211773934303915373692342452941929761641411569,
    ),
    (
        2.897153057105493432130432594192938764924887287701866490314866693455023795137503079289,
        -6.359448489975074843148159912383825625952700647415626703305928850207288721235210244366,
        4.362295432869581411017727318190886861027813359713760212991062156752264926097707165077,
    ),
    (
        5.325864828439256604428877920840511317836476253097040101202360397727981648835607691791,
        -11.74888356406282787774717033978577296188744178259862899288666928009020615663593781589,
        7.495539342889836208304604784564358155658679161518186721010132816213648793440552049753,
        -0.9249506636175524925650207933207191611349983406029535244034750452930469056411389539635e-1,
    ),
    (
        5.861455442946420028659251486982647890394337666164814434818157239052507339770711679748,
        -12.92096931784710929170611868178335939541780751955743459166312250439928519268343184452,
        8.159367898576158643180400794539253485181918321135053305748355423955009222648673734986,
        -0.7158497328140099722453054252582973869127213147363544882721139659546372402303777878835e-1,
        -0.2826905039406838290900305721271224146717633626879770007617876201276764571291579142206e-1,
    ),
)

# Weights of the propagated 5th-order solution (b7 = 0).
_TSIT5_B = (
    0.9646076681806522951816731316512876333711995238157997181903319145764851595234062815396e-1,
    0.01,
    0.4798896504144995747752495322905965199130404621990332488332634944254542060153074523509,
    1.379008574103741893192274821856872770756462643091360525934940067397245698027561293331,
    -3.290069515436080679901047585711363850115683290894936158531296799594813811049925401677,
    2.324710524099773982415355918398765796109060233222962411944060046314465391054716027841,
    0.0,
)

# Error weights e = b − b̂ (the sign convention of diffrax `b_error` and torchode `b_err`).
_TSIT5_E = (
    1.780011052225771443378550607539534775944678804333659557637450799792588061629796e-03,
    8.164344596567469032236360633546862401862537590159047610940604670770447527463931e-04,
    -7.880878010261996010314727672526304238628733777103128603258129604952959142646516e-03,
    1.44711007173262907537165147972635116720922712343167677619514233896760819649515e-01,
    -5.823571654525552250199376106520421794260781239567387797673045438803694038950012e-01,
    4.580821059291869466616365188325542974428047279788398179474684434732070620889539e-01,
    -1.0 / 66.0,
)

# Free 4th-order dense output: y(t0 + θh) = y0 + h Σ_i b_i(θ) k_i with
#   b_1(θ) = θ (r11 + r12 θ + r13 θ² + r14 θ³),  b_i(θ) = θ² (r_i2 + r_i3 θ + r_i4 θ²), i ≥ 2.
# Stored as the coefficients of θ, θ², θ³, θ⁴ for each stage: row i = (p1, p2, p3, p4).
_TSIT5_INTERP = (
    (
        0.999999999999999974283372471559910888475488471328,
        -2.763706197274825911336735930481400260916070804192,
        2.91325546182191274375068099306808,
        -1.0530884977290216,
    ),
    (0.0, 0.13169999999999999727, -0.22339999999999999818, 0.1017),
    (
        0.0,
        3.93029623689475152850687446709813398,
        -5.94103387213150473470249202589458001,
        2.490627285651252793,
    ),
    (
        0.0,
        -12.411077166933676983734381540685453484102414134010752,
        30.3381886302823215981729903691836576,
        -16.54810288924490272,
    ),
    (
        0.0,
        37.50931341651103919496903965334519631242339792120440212,
        -88.1789048947664011014276693541209817,
        47.37952196281928122,
    ),
    (
        0.0,
        -27.896526289197287805948263144598643896,
        65.09189467479367152629021928716553658,
        -34.87065786149660974,
    ),
    (0.0, 1.5, -4.0, 2.5),
)


TSIT5 = ButcherTableau(
    name="tsit5",
    summary="Tsitouras 5(4), adaptive",
    c=_TSIT5_C,
    a=(*_TSIT5_A, _TSIT5_B[:-1]),
    b=_TSIT5_B,
    e=_TSIT5_E,
    interp=_TSIT5_INTERP,
    order=5,
    error_order=4,
    dense_order=4,
    fsal=True,
)


def _q(*values: Fraction | int) -> tuple[float, ...]:
    """Exact rationals → float64, each rounded once."""
    return tuple(float(Fraction(v)) for v in values)


F = Fraction
_DOPRI5_B = _q(F(35, 384), 0, F(500, 1113), F(125, 192), F(-2187, 6784), F(11, 84), 0)
# e = b − b̂ with b̂ = (5179/57600, 0, 7571/16695, 393/640, −92097/339200, 187/2100, 1/40).
_DOPRI5_E = _q(F(71, 57600), 0, F(-71, 16695), F(71, 1920), F(-17253, 339200), F(22, 525),
               F(-1, 40))

DOPRI5 = ButcherTableau(
    name="dopri5",
    summary="Dormand–Prince 5(4), adaptive",
    c=_q(0, F(1, 5), F(3, 10), F(4, 5), F(8, 9), 1, 1),
    a=(
        (),
        _q(F(1, 5)),
        _q(F(3, 40), F(9, 40)),
        _q(F(44, 45), F(-56, 15), F(32, 9)),
        _q(F(19372, 6561), F(-25360, 2187), F(64448, 6561), F(-212, 729)),
        _q(F(9017, 3168), F(-355, 33), F(46732, 5247), F(49, 176), F(-5103, 18656)),
        _DOPRI5_B[:-1],
    ),
    b=_DOPRI5_B,
    e=_DOPRI5_E,
    # Shampine (1986) as in scipy's RK45.P: coefficients of θ, θ², θ³, θ⁴ per stage.
    interp=(
        _q(1, F(-8048581381, 2820520608), F(8663915743, 2820520608),
           F(-12715105075, 11282082432)),
        _q(0, 0, 0, 0),
        _q(0, F(131558114200, 32700410799), F(-68118460800, 10900136933),
           F(87487479700, 32700410799)),
        _q(0, F(-1754552775, 470086768), F(14199869525, 1410260304),
           F(-10690763975, 1880347072)),
        _q(0, F(127303824393, 49829197408), F(-318862633887, 49829197408),
           F(701980252875, 199316789632)),
        _q(0, F(-282668133, 205662961), F(2019193451, 616988883), F(-1453857185, 822651844)),
        _q(0, F(40617522, 29380423), F(-110615467, 29380423), F(69997945, 29380423)),
    ),
    order=5,
    error_order=4,
    dense_order=4,
    fsal=True,
)

_RK4_B = _q(F(1, 6), F(1, 3), F(1, 3), F(1, 6))

RK4 = ButcherTableau(
    name="rk4",
    summary="classic 4th order, fixed steps only",
    c=_q(0, F(1, 2), F(1, 2), 1),
    a=((), _q(F(1, 2)), _q(0, F(1, 2)), _q(0, 0, 1)),
    b=_RK4_B,
    e=None,
    # Cubic Hermite from y₀, y₁ = y₀ + h Σ b_i k_i, f₀ = k₁ and f₁ = f(t₀ + h, y₁):
    #   y(θ) = y₀ + (3θ² − 2θ³)(y₁ − y₀) + (θ − 2θ² + θ³) h f₀ + (θ³ − θ²) h f₁,
    # so b_i(θ) = b_i (3θ² − 2θ³) + [i = 1](θ − 2θ² + θ³) + [i = end](θ³ − θ²).
    interp=(
        _q(1, F(-3, 2), F(2, 3)),
        _q(0, 1, F(-2, 3)),
        _q(0, 1, F(-2, 3)),
        _q(0, F(1, 2), F(-1, 3)),
        _q(0, -1, 1),
    ),
    order=4,
    error_order=None,
    dense_order=3,
    fsal=False,
)
del F

METHODS: dict[str, ButcherTableau] = {t.name: t for t in (TSIT5, DOPRI5, RK4)}


def get_method(name: str, fixed_dt: float | None) -> ButcherTableau:
    """The tableau of method `name`, checked to be usable with this `fixed_dt`.

    Raises:
        ValueError: an unknown name, or a method without error estimate and no fixed_dt.
    """
    if name not in METHODS:
        raise ValueError(f"unknown solver method '{name}' (choose from: {', '.join(METHODS)})")
    tableau = METHODS[name]
    if fixed_dt is None and not tableau.adaptive:
        raise ValueError(f"method '{name}' has no error estimate, so it only takes fixed "
                         "steps: give fixed_dt (--fixed-dt)")
    return tableau
