-- ArduPilot's scripting bindings as triswarm.lua uses them, faked for a unit test of the script's
-- logic (tests/test_ardupilot_script.py): every call the script makes is recorded in H, and H holds
-- the vehicle's state the test sets. Not ArduPilot: the firmware test runs the script on the real one.
H = {t_ms = 0, armed = false, mode = 0, estop = false, safety = false, sysid = 1, params = {},
     outputs = {}, calls = {}, texts = {}, named = {}, queue = {}, gyro = {0, 0, 0}}

local function ud(v) return {tofloat = function(_) return v end} end

function millis() return ud(H.t_ms) end
function micros() return ud(H.t_ms * 1000) end

local function record(name, ...) H.calls[#H.calls + 1] = {name, ...} end

param = {
  add_table = function(_, key, prefix, n) return true end,
  add_param = function(_, key, index, name, default)
    if H.params["TSW_" .. name] == nil then H.params["TSW_" .. name] = default end
    return true
  end,
}

function Parameter()
  local p = {}
  function p:init(name)
    if H.params[name] == nil then return false end
    self.name = name
    return true
  end
  function p:get() return H.params[self.name] end
  return p
end

vehicle = {
  get_mode = function(_) return H.mode end,
  set_mode = function(_, m) record("set_mode", m); H.mode = m; return true end,
  set_target_rate_and_throttle = function(_, p, q, r, thrust) record("track", p, q, r, thrust); return true end,
}
arming = {is_armed = function(_) return H.armed end}
SRV_Channels = {
  get_emergency_stop = function(_) return H.estop end,
  get_safety_state = function(_) return H.safety end,
  set_output_pwm_chan_timeout = function(_, chan, pwm, timeout_ms)
    record("pwm", chan, pwm, timeout_ms)
    H.outputs[chan] = {pwm, timeout_ms}
  end,
}
rc = {run_aux_function = function(_, fn, pos) record("aux", fn, pos); return true end}
gcs = {
  send_text = function(_, sev, text) H.texts[#H.texts + 1] = text end,
  send_named_float = function(_, name, value) H.named[#H.named + 1] = {name, value} end,
}
ahrs = {get_gyro = function(_)
  return {x = function(_) return H.gyro[1] end, y = function(_) return H.gyro[2] end, z = function(_) return H.gyro[3] end}
end}
mavlink = {
  init = function(_, n, m) end,
  register_rx_msgid = function(_, id) return true end,
  receive_chan = function(_)
    local item = table.remove(H.queue, 1)
    if item == nil then return nil end
    return item[1], 0, ud(item[2])
  end,
}
