"""Index layout of the flat arrays that cross into the kernels.

Module-level integers are compile-time constants for numba.
"""

# --- FASTMATH choice for all kernels: only "contract", i.e. LLVM may fuse a*b + c
# into one fused multiply-add (one rounding instead of two; the Horner chains of
# the property polynomials and the flow solves become shorter).  Measured 6-8 %
# less time per cycle (A/B, same process, best of 15).  The other fast-math
# flags stay off: the model relies on exact IEEE behaviour in a few places
# (min/max clamps, NaN detection on failure).
FASTMATH = {"contract"}

# --- Reference counting: every kernel except the driver ``run_engine`` (which
# allocates its work arrays) is compiled with ``_nrt=False``.  Numba otherwise
# increments and decrements (atomically) the reference count of every array
# argument on entry to and exit from each call; the kernels call their small
# helpers (property evaluation, flow elements, transfers) tens of times per
# step, and those atomic operations cost ~10-40 % of a cycle.  A kernel compiled
# this way cannot allocate arrays (numba then refuses to compile it).

# ------------------------------------------------------------------ species
SP_A = 0   # air
SP_M = 1   # fresh mixture (air + fuel vapour at the point's lambda)
SP_P = 2   # burned products of M

# ------------------------------------------------------------------ volume state columns
V_MA = 0   # mass of air [kg]
V_MM = 1   # mass of fresh mixture [kg]
V_MP = 2   # mass of products [kg]
V_U = 3    # total internal energy incl. formation enthalpies [J]
V_T = 4    # temperature [K] (derived; kept as Newton warm start)
NVCOL = 5

# ------------------------------------------------------------------ scalar parameters (par array)
P_DT = 0            # time step [s]
P_NSTEP = 1         # steps per 720 deg cycle
P_NCYL = 2
P_PAMB = 3          # ambient pressure [Pa]
P_TAMB = 4          # ambient temperature [K]
P_FAR = 5           # fuel/air mass ratio [-]
P_VD = 6            # swept volume of one cylinder [m3]
P_SP = 7            # mean piston speed [m/s]
P_WOSCHNI = 8       # 3.26 * B^-0.2 * multiplier  [SI with p in kPa]
P_C1_GE = 9
P_C1_CL = 10
P_C2 = 11
P_TW_HEAD = 12
P_TW_PISTON = 13
P_TW_LINER = 14
P_A_HEAD = 15       # head area [m2]
P_A_PISTON = 16     # piston crown area [m2]
P_THR_CDA = 17      # throttle effective area [m2]
P_RES_CDA = 18      # restrictor effective throat area [m2]
P_RES_REC = 19      # diffuser pressure recovery [-]
P_IR_A = 20         # intake runner cross-section [m2]
P_IR_L = 21         # intake runner length [m]
P_IR_K = 22         # intake runner loss factor: exit dump + minor losses + wall friction [-]
P_IR_INERTIA = 23   # 1 = momentum equation, 0 = quasi-steady
P_ER_A = 24
P_ER_L = 25
P_ER_K = 26
P_ER_INERTIA = 27
P_TP_CDA = 28       # tailpipe effective area [m2]
P_KN_A = 29         # Douaud-Eyzat A*(ON/100)^a times the calibrated delay multiplier [s]
P_KN_N = 30         # pressure exponent [-]
P_KN_B = 31         # activation temperature [K]
P_COMBUSTION = 32   # 1 = fired, 0 = motored
P_MAXCYC = 33       # cycle cap
P_TOL = 34          # relative convergence tolerance
P_IDX_IVC = 35      # local step index of IVC
P_IDX_EVO = 36
P_IDX_SOC = 37
P_MINCYC = 38       # minimum cycles before convergence may be declared
P_IR_NSEG = 39      # lumped segments per intake runner (>= 1; 1 when quasi-steady)
P_ACCEL_K = 40      # modes removed per MPE extrapolation of the cycle iteration (0 = plain iteration)
P_NET_EPS = 41      # orifice law continued linearly below 1 - p_dn/p_up < eps [-] (finite conductance at equal pressures)
P_ER_NSEG = 42      # lumped segments per exhaust runner
P_ACCEL_WARM = 43   # first cycle whose end state enters the MPE window
P_GASX = 44         # gas exchange: 0 = lumped runners, 1 = quasi-1D pipes
P_CFL = 45          # Courant number of the pipe sub-steps [-]
P_EVAP = 46         # latent heat the port-injected fuel takes from the charge [J per kg of fuel]
P_PHT_MULT = 47     # multiplier on the port wall heat-transfer coefficient [-]
P_PHT_A_IN = 48     # intake port wall area [m2]
P_PHT_D_IN = 49     # intake port hydraulic diameter [m]
P_PHT_TW_IN = 50    # intake port wall temperature [K]
P_PHT_A_EX = 51     # exhaust port wall area [m2]
P_PHT_D_EX = 52     # exhaust port hydraulic diameter [m]
P_PHT_TW_EX = 53    # exhaust port wall temperature [K]
P_FRIC_EVERY = 54   # pipe friction factors refreshed every this many pipe sub-steps
P_KN_D = 55         # dilution exponent d of the ignition delay, tau ~ (1 - x_burned)^-d [-]
NPAR = 56

# ------------------------------------------------------------------ runner state array (mr)
# lumped gas exchange: mr[: ncyl * (nseg_in + nseg_ex)] are the runner segment mass flows [kg/s]
# 1D gas exchange: mr is empty; the pipes' cell state is q[ncell, NQ] (see pipes.py)

# ------------------------------------------------------------------ pipe-end table (ends[ip, side, :])
E_KIND = 0     # boundary kind (BC_*)
E_VOL = 1      # volume on the other side (nvol = ambient)
NE = 2
BC_OPEN = 1    # open end into a volume (pipe_bc.bc_open), endp[ip, side, 0] = entry loss k [-]
BC_ORIFICE = 2  # orifice to a volume (pipe_bc.bc_orifice), endp[..., 0] = CdA out, endp[..., 1] = CdA in [m2]
NEP = 2

# ------------------------------------------------------------------ per-angle tables (tab[row, local_idx])
T_V = 0        # cylinder volume [m3]
T_ALINER = 1   # exposed liner area [m2]
T_AIV = 2      # intake valve effective area (Cd * curtain * n) [m2]
T_AEV = 3      # exhaust valve effective area [m2]
T_XB = 4       # Wiebe burned fraction [-]
T_VMOT = 5     # (V_ivc / V)^gamma_mot for the Woschni motored pressure [-]
T_PHASE = 6    # 0 gas exchange, 1 closed before SOC, 2 combustion/expansion
T_KWIN = 7     # share of the crank step starting here inside the knock window (IVC .. end gas consumed) [0-1]
NTAB = 8

# ------------------------------------------------------------------ cycle outputs (out array)
O_AIR = 0          # air mass through the throttle per cycle [kg]
O_FUEL = 1         # fuel injected per cycle [kg]
O_EXH = 2          # mass out of the tailpipe per cycle [kg]
O_WGROSS = 3       # gross indicated work, all cylinders [J]
O_WPUMP = 4        # gas-exchange-loop work, all cylinders [J] (negative = pumping loss)
O_QWALL = 5        # in-cylinder wall heat loss, all cylinders [J]
O_PMAX = 6         # mean over cylinders of peak pressure [Pa]
O_PMAX_ANG = 7     # mean over cylinders of its angle [deg ATDC]
O_TEXH = 8         # mass-averaged temperature of gas leaving the exhaust valves [K]
O_RES = 9          # mean burned-gas mass fraction at IVC [-]
O_KNOCK = 10       # max over cylinders of the Livengood-Wu integral [-]
O_MTRAP = 11       # trapped mass at IVC, all cylinders [kg]
O_CYCLES = 12
O_CONVERGED = 13
O_HAIR = 14        # enthalpy of air in through the throttle [J]
O_HFUEL = 15       # enthalpy (incl. formation) of fuel injected [J]
O_HOUT = 16        # enthalpy out through the tailpipe [J]
O_MBAL = 17        # |in - out| / in over the last cycle [-]
O_FAIL = 18        # 0 ok, 1 non-finite state, 2 negative mass / pressure
O_FUEL_BURNED = 19 # fuel mass converted to products per cycle [kg]
O_PPLENUM = 20     # cycle-mean plenum pressure [Pa]
O_DTRAP = 21       # last relative change of trapped mass [-]
O_DIMEP = 22       # last relative change of net work [-]
O_MAIR_TRAP = 23   # fresh charge (air+fuel) trapped at IVC, all cylinders [kg]
O_EST = 24         # estimated relative distance of the last cycle to the periodic solution [-]
O_QPORT = 25       # heat into the ports from their walls, all ports [J] (negative = to the walls)
O_QPIPE = 26       # heat into the pipes' gas from their walls [J] (1D)
O_SUBSTEPS = 27    # largest number of pipe sub-steps per crank step in the last cycle (1D)
O_COURANT = 28     # largest Courant number of a whole crank step in the last cycle (1D)
NOUT = 29

# ------------------------------------------------------------------ traces of the last cycle (trace[row, global_idx])
TR_P_CYL0 = 0      # rows 0..ncyl-1: cylinder pressures [Pa]
# then: ncyl rows of cylinder temperatures, plenum pressure, collector pressure,
# throttle-body pressure, intake-port-1 pressure, exhaust-port-1 pressure, then (1D; port pressures
# when lumped) the pressure in intake runner 1 at its middle and at its port end, and in exhaust
# primary 1 at its port end and its middle [Pa]
NTR_EXTRA = 9      # rows after the 2 * ncyl cylinder rows

# ------------------------------------------------------------------ per-cycle history (hist[cycle-1, col])
H_MTRAP = 0        # trapped mass at IVC, all cylinders [kg]
H_WNET = 1         # net indicated work, all cylinders [J]
H_MBAL = 2         # |in - out| / in of the cycle [-]
H_N0 = 3           # then the end-of-cycle state: vol[:, :NVCOL-1] row by row, then mr
