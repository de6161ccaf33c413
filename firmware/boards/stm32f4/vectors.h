/* The exception and interrupt handlers of startup.c's vector table; a board defines those it uses
 * (the rest are weak aliases of default_handler). */
#ifndef FW_VECTORS_H
#define FW_VECTORS_H

void reset_handler(void);
void default_handler(void);
void nmi_handler(void);
void hardfault_handler(void);
void memmanage_handler(void);
void busfault_handler(void);
void usagefault_handler(void);
void svc_handler(void);
void debugmon_handler(void);
void pendsv_handler(void);
void systick_handler(void);
void exti1_handler(void);

#endif
