// Preloaded into the CNCjs server (`node --require exit-with-parent.js …`): the server exits
// when the process that started it is gone, so that a driver killed outright leaves no server
// holding the simulator's pseudo-terminal and a port.
'use strict';

const parent = process.ppid;
setInterval(() => {
  if (process.ppid !== parent) {
    process.exit(1);
  }
}, 500).unref();
