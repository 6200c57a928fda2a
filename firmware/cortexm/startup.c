/*
 * startup.c - vector table, reset handler and semihosting for the Cortex-M7
 * test images. Reset copies .data, zeroes .bss and turns the FPU on (CPACR
 * CP10/CP11 full access) before main, because main's code is hard-float.
 */
#include <stdint.h>

#include "semihost.h"

extern uint32_t _data_load, _data_start, _data_end, _bss_start, _bss_end, _stack_top;
int main(void);

void reset_handler(void);
static void fault_handler(void);

__attribute__((section(".vectors"), used)) static const void *const vectors[16] = {
    &_stack_top, (void *)reset_handler, (void *)fault_handler, (void *)fault_handler,
    (void *)fault_handler, (void *)fault_handler, (void *)fault_handler, 0, 0, 0, 0,
    (void *)fault_handler, (void *)fault_handler, 0, (void *)fault_handler,
    (void *)fault_handler,
};

void reset_handler(void)
{
    volatile uint32_t *cpacr = (volatile uint32_t *)0xE000ED88u;
    *cpacr |= (0xFu << 20);
    __asm volatile("dsb\n\tisb" ::: "memory");
    for (uint32_t *src = &_data_load, *dst = &_data_start; dst < &_data_end;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_bss_start; dst < &_bss_end;) {
        *dst++ = 0u;
    }
    sh_exit(main());
}

static void fault_handler(void)
{
    sh_puts("FAULT\n");
    sh_exit(3);
}

static int semihost(int op, const void *arg)
{
    register int r0 __asm("r0") = op;
    register const void *r1 __asm("r1") = arg;
    __asm volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void sh_puts(const char *s)
{
    semihost(0x04, s); /* SYS_WRITE0 */
}

void sh_exit(int code)
{
    /* SYS_EXIT_EXTENDED (0x20): ADP_Stopped_ApplicationExit with an exit code */
    uint32_t block[2] = {0x20026u, (uint32_t)code};
    semihost(0x20, block);
    semihost(0x18, (const void *)0x20026u); /* plain SYS_EXIT if the host lacks 0x20 */
    for (;;) {
    }
}

void sh_put_hex32(uint32_t v)
{
    char buf[9];
    for (int i = 7; i >= 0; --i) {
        buf[i] = "0123456789abcdef"[v & 0xFu];
        v >>= 4;
    }
    buf[8] = '\0';
    sh_puts(buf);
}

void sh_put_dec(int32_t v)
{
    char buf[12];
    int i = 11;
    uint32_t u = (v < 0) ? (uint32_t)(-(v + 1)) + 1u : (uint32_t)v;
    buf[i] = '\0';
    do {
        buf[--i] = (char)('0' + u % 10u);
        u /= 10u;
    } while (u != 0u);
    if (v < 0) {
        buf[--i] = '-';
    }
    sh_puts(&buf[i]);
}

void systick_start(void)
{
    volatile uint32_t *syst = (volatile uint32_t *)0xE000E010u;
    syst[0] = 0u;          /* CSR: off */
    syst[1] = 0x00FFFFFFu; /* RVR: full 24-bit range */
    syst[2] = 0u;          /* CVR: any write clears */
    syst[0] = 5u;          /* CSR: enable, processor clock, no interrupt */
}
