/*
 * Minimal Arm semihosting and bare-metal helpers for the QEMU runs
 * (qemu-system-arm -M mps2-an500 -semihosting): print a string, exit, read the
 * SysTick counter. No stdio, so the harness adds next to nothing to the size.
 */
#ifndef COVEY_SEMIHOST_H
#define COVEY_SEMIHOST_H

#include <stdint.h>

void sh_puts(const char *s);              /* SYS_WRITE0 */
void sh_exit(int code);                   /* SYS_EXIT(_EXTENDED) */
void sh_put_hex32(uint32_t v);            /* 8 hex digits, no newline */
void sh_put_dec(int32_t v);               /* decimal, no newline */

/* SysTick, counting down from 2^24 - 1 at the core clock (25 MHz on MPS2). */
void systick_start(void);
static inline uint32_t systick_now(void) { return *(volatile uint32_t *)0xE000E018u; }
/* ticks elapsed between two systick_now() readings (24-bit down counter) */
static inline uint32_t systick_elapsed(uint32_t start, uint32_t end)
{
    return (start - end) & 0x00FFFFFFu;
}

#endif
