-- wrk script of benchmarks/load_localize.py (--generator wrk): each connection
-- posts the pre-generated request bodies of LANEMAP_BODIES (one JSON document
-- per line) in turn to LANEMAP_PATH, closed loop; after a 503 the connection
-- waits Retry-After, as the Python client and a vehicle do. At the end it prints one line
-- "RESULT {json}" with the latency percentiles of all answers, counts per
-- status, the socket errors and the localizer's median time from Server-Timing.
-- The counters live in each wrk thread; done() (in wrk's main Lua state) reads
-- them through setup()'s thread handles.

local bodies = {}
local path = os.getenv("LANEMAP_PATH")
for line in io.lines(os.getenv("LANEMAP_BODIES")) do
  if #line > 0 then bodies[#bodies + 1] = line end
end

local i = 0
statuses = {}
localize_ms = {}
local n_localize = 0
local headers = { ["Content-Type"] = "application/json" }
local threads = {}

setup = function(thread)
  threads[#threads + 1] = thread
end

request = function()
  i = i % #bodies + 1
  return wrk.format("POST", path, headers, bodies[i])
end

-- wrk asks delay() before each connection's next request, after that
-- connection's response(). delay() knows no connection: when two answers
-- arrive in one turn of wrk's event loop, the wait may go to the other one
-- (the number of waits stays that of the 503s).
local backoff = 0
delay = function()
  local d = backoff
  backoff = 0
  return d
end

response = function(status, hdrs, body)
  statuses[status] = (statuses[status] or 0) + 1
  if status == 503 then
    backoff = 1000 * (tonumber(hdrs["Retry-After"] or hdrs["retry-after"]) or 1)
  end
  if status == 200 then
    local st = hdrs["Server-Timing"] or hdrs["server-timing"]
    if st then
      local v = string.match(st, "localize;dur=([%d%.]+)")
      if v and n_localize < 200000 then
        n_localize = n_localize + 1
        localize_ms[n_localize] = tonumber(v)
      end
    end
  end
end

done = function(summary, latency, requests)
  local all, counts = {}, {}
  for _, t in ipairs(threads) do
    for _, v in ipairs(t:get("localize_ms") or {}) do all[#all + 1] = v end
    for s, n in pairs(t:get("statuses") or {}) do counts[s] = (counts[s] or 0) + n end
  end
  table.sort(all)
  local loc = all[math.max(1, math.floor((#all + 1) / 2))] or -1
  local parts = {}
  for s, n in pairs(counts) do parts[#parts + 1] = string.format('"%d": %d', s, n) end
  local e = summary.errors
  io.write(string.format(
    'RESULT {"duration_us": %d, "requests": %d, "p50_us": %d, "p90_us": %d, "p99_us": %d, ' ..
    '"max_us": %d, "statuses": {%s}, "errors": {"connect": %d, "read": %d, "write": %d, ' ..
    '"timeout": %d, "status": %d}, "localize_p50_ms": %.3f}\n',
    summary.duration, summary.requests, latency:percentile(50), latency:percentile(90),
    latency:percentile(99), latency.max, table.concat(parts, ", "), e.connect, e.read, e.write,
    e.timeout, e.status, loc))
end
