/* ARM semihosting (the Arm "Semihosting for AArch32 and AArch64" specification): on M-profile a
 * `bkpt 0xab` with the operation in r0 and its argument block in r1. QEMU (-semihosting-config
 * enable=on,target=native) serves the console ":tt" from its own stdin and stdout. */
#ifndef FW_SEMIHOST_H
#define FW_SEMIHOST_H

#include <stddef.h>
#include <stdint.h>

/* Open the console for reading (0) or writing (1); the handle, or -1. */
int semihost_console(int write);

/* Read up to len bytes, blocking until at least one is there (QEMU reads its stdin); the count read. */
size_t semihost_read(int handle, void *buf, size_t len);

void semihost_write(int handle, const void *buf, size_t len);

#endif
