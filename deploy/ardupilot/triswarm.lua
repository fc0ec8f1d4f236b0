--[[
triswarm: the companion computer drives the three motors and the three tilt servos of a tri-rotor
whose rotors tilt independently (ArduCopter 4.6 or later, scripting enabled; see triswarm.parm).

The companion (system MAV_SYSID, component TSW_SRC_COMP) sends SET_ACTUATOR_CONTROL_TARGET, group 0:
  controls[1..3]  rotor speeds, as a fraction of the top speed TSW_MAX_RPM (0..1)
  controls[4..6]  tilt angles, as a fraction of the servo limit TSW_SRV_DEG (-1..1)
  time_usec       this flight controller's time [us since boot] of the telemetry the command answers
and this script turns them into PWM on the outputs TSW_MOT_CH.. and TSW_SRV_CH.. (three each):
  motor  TSW_MOT_MIN + c * (TSW_MOT_MAX - TSW_MOT_MIN)
  servo  TSW_SRV_TRIM + c * TSW_SRV_SPAN

A motor override bypasses ArduPilot's disarm, emergency stop and safety switch, so the script drives
the outputs only while ALL of these hold, and checks them on every run:
  - armed, no emergency stop, the safety switch off (outputs live);
  - in the companion's mode TSW_MODE (GUIDED: the mode whose targets a script can set);
  - the newest command is fresh: received less than TSW_CMD_TOUT ms ago, and answering telemetry
    less than TSW_CMD_TOUT ms old.
While it drives the outputs it keeps ArduPilot's own controllers where the vehicle is: with every
command applied, their targets are the vehicle's own body rates and the collective thrust the
companion commands (GUIDED's rate and thrust control), so they see no error to integrate, keep
their motors spooled up and the vehicle in the air, and a handover starts from the state the
vehicle is in, not from wound-up integrators or a target left behind; and "force flying" is on (ArduPilot's land detector and crash check judge the vehicle by its own
controllers' outputs and targets, which the companion's overrides make meaningless: a tri-rotor
that holds 0.5 rad of roll while hovering is no crash). Each command is set with a timeout of
TSW_CMD_TOUT ms: if the commands stop (or this script stops),
the overrides lapse by themselves within TSW_CMD_TOUT and ArduPilot's own outputs take over. When a
condition fails (disarmed, E-stop, safety on, another mode) the overrides are released at once.

Failsafe: in TSW_MODE, armed, with no fresh command for TSW_CMD_TOUT ms (the companion stopped, or
its link did), the script switches to TSW_FS_MODE (BRAKE: ArduPilot stops the vehicle where it is
and holds). Fresh commands within TSW_FS_LAND_S switch it back to TSW_MODE (the companion came
back); after TSW_FS_LAND_S without them it switches to LAND. A mode the operator chose is never
undone: only the failsafe's own mode is won back or turned into LAND.

Once a second it reports to every MAVLink channel (NAMED_VALUE_FLOAT):
  TSW_HZ    commands applied in the last second
  TSW_AGE   the oldest applied command's age in that second [ms] (telemetry to output)
  TSW_DROP  commands dropped since boot (wrong sender or target, not finite, out of date)
  TSW_STATE 0 released, 1 driving the outputs, 2 failsafe (also at once on every change)
and a STATUSTEXT on every change of state, with the reason.
--]]

local SCRIPT_PERIOD_MS = 1
local PARAM_TABLE_KEY = 73
local PARAM_TABLE_PREFIX = "TSW_"
local MSG_SET_ACTUATOR_CONTROL_TARGET = 139
local MODE_BRAKE, MODE_LAND = 17, 9
local AUX_FORCE_FLYING, AUX_HIGH, AUX_LOW = 159, 2, 0
local SEVERITY = {CRITICAL = 2, WARNING = 4, INFO = 6}

local function bind_add_param(name, index, default)
  assert(param:add_param(PARAM_TABLE_KEY, index, name, default), "triswarm: could not add param " .. name)
  local p = Parameter()
  assert(p:init(PARAM_TABLE_PREFIX .. name), "triswarm: could not find param " .. name)
  return p
end

assert(param:add_table(PARAM_TABLE_KEY, PARAM_TABLE_PREFIX, 16), "triswarm: could not add the TSW_ param table")
-- 1: drive the outputs from the companion's commands; 0: this script does nothing
local TSW_ENABLE = bind_add_param("ENABLE", 1, 1)
-- the companion's flight mode: GUIDED (4), whose controllers' targets this script keeps on the vehicle
local TSW_MODE = bind_add_param("MODE", 2, 4)
-- a command older than this [ms] is not applied; overrides lapse this long after the last one
local TSW_CMD_TOUT = bind_add_param("CMD_TOUT", 3, 200)
-- the mode to switch to when the commands stop in TSW_MODE (-1: none)
local TSW_FS_MODE = bind_add_param("FS_MODE", 4, MODE_BRAKE)
-- this long in TSW_FS_MODE without fresh commands [s], then LAND (0: stay)
local TSW_FS_LAND_S = bind_add_param("FS_LAND_S", 5, 5)
-- the companion's MAVLink component id (its system id is this vehicle's)
local TSW_SRC_COMP = bind_add_param("SRC_COMP", 6, 191)
-- the first of the three motor outputs (SERVOn, 1-based), rotors 1, 2, 3 in order
local TSW_MOT_CH = bind_add_param("MOT_CH", 7, 1)
-- the first of the three tilt-servo outputs (SERVOn, 1-based)
local TSW_SRV_CH = bind_add_param("SRV_CH", 8, 4)
-- PWM of a stopped rotor, and of a rotor at TSW_MAX_RPM [us]
local TSW_MOT_MIN = bind_add_param("MOT_MIN", 9, 1000)
local TSW_MOT_MAX = bind_add_param("MOT_MAX", 10, 2000)
-- PWM of an untilted rotor, and from there to the servo limit TSW_SRV_DEG [us]
local TSW_SRV_TRIM = bind_add_param("SRV_TRIM", 11, 1500)
local TSW_SRV_SPAN = bind_add_param("SRV_SPAN", 12, 500)
-- the rotors' top speed [RPM] and the servos' limit [deg]: what a control of 1 means (read by the companion)
bind_add_param("MAX_RPM", 13, 12000)
bind_add_param("SRV_DEG", 14, 120)

local function bind_param(name)
  local p = Parameter()
  assert(p:init(name), "triswarm: no " .. name .. " parameter")
  return p
end
local MOT_PWM_MIN, MOT_PWM_MAX = bind_param("MOT_PWM_MIN"), bind_param("MOT_PWM_MAX")

local MAV_SYSID = Parameter()
if not MAV_SYSID:init("MAV_SYSID") then
  assert(MAV_SYSID:init("SYSID_THISMAV"), "triswarm: no MAV_SYSID parameter")
end

mavlink:init(4, 1)
mavlink:register_rx_msgid(MSG_SET_ACTUATOR_CONTROL_TARGET)

local newest = nil        -- {rx_ms, time_usec, controls = {6 numbers}}
local driving = false     -- overrides set and not yet released
local state, state_reason = 0, ""
local failsafe_since_ms = nil   -- when the script switched to TSW_FS_MODE
local applied_n, oldest_age_ms, dropped = 0, 0, 0
local report_ms = 0

local function say(severity, text)
  gcs:send_text(severity, "triswarm: " .. text)
end

local function finite(x)
  return x == x and x > -math.huge and x < math.huge
end

-- the fields of a SET_ACTUATOR_CONTROL_TARGET (the raw mavlink_message_t: payload from byte 13)
local function take(msg, rx_ms)
  local src_sys, src_comp = string.unpack("<BB", msg, 8)
  local time_usec, c1, c2, c3, c4, c5, c6, _, _, group, target_sys, target_comp =
    string.unpack("<i8ffffffffBBB", msg, 13)
  if src_sys ~= MAV_SYSID:get() or src_comp ~= TSW_SRC_COMP:get() or group ~= 0
     or target_sys ~= MAV_SYSID:get() or (target_comp ~= 0 and target_comp ~= 1) then
    dropped = dropped + 1
    return
  end
  local c = {c1, c2, c3, c4, c5, c6}
  for i = 1, 6 do
    if not finite(c[i]) then  -- (a command of NaNs says: nothing to command)
      dropped = dropped + 1
      return
    end
  end
  newest = {rx_ms = rx_ms, time_usec = time_usec, controls = c}
end

local function clamp(x, lo, hi)
  return math.max(lo, math.min(hi, x))
end

-- the newest command on the outputs, for timeout_ms; returns the three motor PWMs
local function set_outputs(timeout_ms)
  local c = newest.controls
  local mot0, srv0 = math.floor(TSW_MOT_CH:get()) - 1, math.floor(TSW_SRV_CH:get()) - 1
  local lo, hi = TSW_MOT_MIN:get(), TSW_MOT_MAX:get()
  local trim, span = TSW_SRV_TRIM:get(), TSW_SRV_SPAN:get()
  local pwm = {}
  for i = 1, 3 do
    pwm[i] = math.floor(lo + clamp(c[i], 0, 1) * (hi - lo) + 0.5)
    SRV_Channels:set_output_pwm_chan_timeout(mot0 + i - 1, pwm[i], timeout_ms)
    SRV_Channels:set_output_pwm_chan_timeout(srv0 + i - 1, math.floor(trim + clamp(c[i + 3], -1, 1) * span + 0.5), timeout_ms)
  end
  return pwm
end

-- release the overrides now: the motors at their stop, the servos untilted, for the one output
-- cycle before ArduPilot's own outputs take over
local function release()
  local mot0, srv0 = math.floor(TSW_MOT_CH:get()) - 1, math.floor(TSW_SRV_CH:get()) - 1
  for i = 0, 2 do
    SRV_Channels:set_output_pwm_chan_timeout(mot0 + i, math.floor(TSW_MOT_MIN:get()), 0)
    SRV_Channels:set_output_pwm_chan_timeout(srv0 + i, math.floor(TSW_SRV_TRIM:get()), 0)
  end
  rc:run_aux_function(AUX_FORCE_FLYING, AUX_LOW)
  driving = false
end

-- ArduPilot's own controllers' targets: the body rates the vehicle turns at, and the collective
-- thrust of the motor PWMs just set, as ArduPilot's throttle (a fraction of its MOT_PWM range,
-- squared: thrust goes with the square of the speed)
local function track(pwm)
  local lo, hi = MOT_PWM_MIN:get(), MOT_PWM_MAX:get()
  local thrust = 0
  for i = 1, 3 do
    thrust = thrust + clamp((pwm[i] - lo) / math.max(1, hi - lo), 0, 1) ^ 2 / 3
  end
  local gyro = ahrs:get_gyro()
  vehicle:set_target_rate_and_throttle(math.deg(gyro:x()), math.deg(gyro:y()), math.deg(gyro:z()), thrust)
end

local function set_state(new, reason)
  if new ~= state or reason ~= state_reason then
    local severity = (new == 2) and SEVERITY.CRITICAL or SEVERITY.INFO
    say(severity, ({[0] = "released", [1] = "driving", [2] = "failsafe"})[new] .. (reason ~= "" and (": " .. reason) or ""))
    if new ~= state then
      gcs:send_named_float("TSW_STATE", new)  -- (at once: the companion tells the failsafe from an operator's mode by it)
    end
    state, state_reason = new, reason
  end
end

-- why the newest command may not be applied now (nil: it is fresh)
local function stale(now_ms)
  if newest == nil then return "no command yet" end
  local tout = TSW_CMD_TOUT:get()
  if now_ms - newest.rx_ms >= tout then return "no command for " .. math.floor(tout) .. " ms" end
  local age_ms = (micros():tofloat() - newest.time_usec) / 1000
  if age_ms >= tout or age_ms < -tout then return "commands out of date" end
  return nil
end

-- why the outputs must not be driven now (nil: they may), and whether only because the commands stopped
local function gate(now_ms)
  if TSW_ENABLE:get() < 1 then return "TSW_ENABLE 0", false end
  if not arming:is_armed() then return "disarmed", false end
  if SRV_Channels:get_emergency_stop() then return "emergency stop", false end
  if SRV_Channels:get_safety_state() then return "safety switch on", false end
  if vehicle:get_mode() ~= math.floor(TSW_MODE:get()) then return "not in the companion's mode", false end
  local why = stale(now_ms)
  return why, why ~= nil and newest ~= nil
end

-- stopped: the outputs are released only because the commands stopped (armed, in the companion's mode)
local function failsafe(now_ms, stopped)
  local mode = vehicle:get_mode()
  if failsafe_since_ms == nil then
    if stopped and TSW_FS_MODE:get() >= 0 then
      if vehicle:set_mode(math.floor(TSW_FS_MODE:get())) then
        failsafe_since_ms = now_ms
        set_state(2, "no fresh command: mode " .. math.floor(TSW_FS_MODE:get()))
      end
    end
    return
  end
  if mode ~= math.floor(TSW_FS_MODE:get()) or not arming:is_armed() then
    failsafe_since_ms = nil  -- someone else chose the mode (or disarmed): theirs now
    return
  end
  if stale(now_ms) == nil and vehicle:set_mode(math.floor(TSW_MODE:get())) then
    failsafe_since_ms = nil
    say(SEVERITY.WARNING, "commands back: companion's mode again")
  elseif TSW_FS_LAND_S:get() > 0 and now_ms - failsafe_since_ms >= 1000 * TSW_FS_LAND_S:get() then
    failsafe_since_ms = nil
    vehicle:set_mode(MODE_LAND)
    set_state(2, "no command for " .. TSW_FS_LAND_S:get() .. " s: LAND")
  end
end

local function report(now_ms)
  if now_ms - report_ms < 1000 then return end
  report_ms = now_ms
  gcs:send_named_float("TSW_HZ", applied_n)
  gcs:send_named_float("TSW_AGE", oldest_age_ms)
  gcs:send_named_float("TSW_DROP", dropped)
  gcs:send_named_float("TSW_STATE", state)
  applied_n, oldest_age_ms = 0, 0
end

local last_applied = nil

local function update()
  local now_ms = millis():tofloat()
  for _ = 1, 4 do  -- (the queue holds four; only the newest command counts)
    local msg, _, rx_ms = mavlink:receive_chan()
    if msg == nil then break end
    take(msg, rx_ms:tofloat())
  end
  local why, stopped = gate(now_ms)
  if why == nil then
    if newest ~= last_applied then
      local pwm = set_outputs(math.floor(TSW_CMD_TOUT:get()))
      last_applied = newest
      applied_n = applied_n + 1
      oldest_age_ms = math.max(oldest_age_ms, (micros():tofloat() - newest.time_usec) / 1000)
      if not driving then
        rc:run_aux_function(AUX_FORCE_FLYING, AUX_HIGH)
        driving = true
      end
      track(pwm)
    end
    set_state(1, "")
  else
    if driving then
      release()
    end
    failsafe(now_ms, stopped)
    if failsafe_since_ms == nil then
      set_state(0, why)
    end
  end
  report(now_ms)
  return update, SCRIPT_PERIOD_MS
end

say(SEVERITY.INFO, "ready: companion's mode " .. math.floor(TSW_MODE:get()))
return update()
